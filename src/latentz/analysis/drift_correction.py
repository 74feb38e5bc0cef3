"""Drift correction of a localization table: by redundant cross-correlation of frame segments
(RCC) or by fiducials; the drift removed is kept as columns, and a figure shows it."""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentz._shared.validate import check_choice, check_int, check_positive
from latentz.analysis.histograms import positions

__all__ = ["correct_drift", "drift_figure", "DRIFT_COLUMNS"]

DRIFT_COLUMNS = ("drift_x_nm", "drift_y_nm", "drift_z_nm")


def _rcc_drift(
    locs: pd.DataFrame, first: int, n_frames: int, segment_frames: int, pixel_nm: float
) -> tuple[np.ndarray, dict]:
    from scipy.interpolate import CubicSpline

    from latentz.analysis.crosscorrelation import rcc_segments

    used = positions(locs, ("frame", "x_nm", "y_nm"))
    blur_z = pixel_nm
    if "z_err_nm" in locs and np.isfinite(locs["z_err_nm"]).any():
        blur_z = max(pixel_nm, float(np.nanmedian(locs.loc[used.index, "z_err_nm"])))
    xyz = used[["x_nm", "y_nm"]].assign(z_nm=locs.loc[used.index, "z_nm"].astype(np.float64))
    centres, segments = rcc_segments(
        xyz,
        used["frame"].to_numpy().astype(np.int64),
        segment_frames=segment_frames,
        pixel_nm=pixel_nm,
        blur_nm=pixel_nm,
        blur_z_nm=blur_z,
    )
    said = {"segments": len(centres)}
    if np.isnan(segments[:, 2]).any():  # 2D data, or segments without z: z is left alone
        segments[:, 2] = 0.0
        said["z"] = "not corrected: some segments have no z"
    spline = CubicSpline(centres, segments, axis=0, bc_type="natural")
    return spline(np.arange(first, first + n_frames)), said


def _fiducial_drift(
    locs: pd.DataFrame, first: int, n_frames: int, radius_nm: float, smooth_frames: int
) -> tuple[np.ndarray, dict]:
    from latentz.analysis.fiducials import fiducial_drift, pick_fiducials

    used = positions(locs, ("frame", "x_nm", "y_nm"))
    xyz = np.column_stack([used[["x_nm", "y_nm"]].to_numpy(), locs.loc[used.index, "z_nm"]])
    index = used["frame"].to_numpy().astype(np.int64) - first
    tracks = pick_fiducials(xyz, index, n_frames, radius_nm=radius_nm, min_fraction=0.8)
    drift, kept = fiducial_drift(tracks, smooth_frames=smooth_frames)
    return drift, {"fiducials": int(kept.sum()), "fiducials_dropped": int((~kept).sum())}


def correct_drift(
    locs: pd.DataFrame,
    *,
    method: str = "rcc",
    segment_frames: int = 1000,
    pixel_nm: float = 20.0,
    fiducial_radius_nm: float = 300.0,
    smooth_frames: int = 100,
) -> pd.DataFrame:
    """The localizations with drift removed from x_nm, y_nm, z_nm, relative to the first frame.

    ``method="rcc"``: the frames are cut into segments of ``segment_frames``; images of the
    segments (``pixel_nm`` pixels, blurred by one pixel) are cross-correlated in every pair and
    the segments' x, y drifts solved from all pairs; then z from x-z and y-z images of the
    laterally corrected segments (blurred by the median z error). A cubic spline through the
    segments' mean frames gives each frame's drift.
    ``method="fiducials"``: emitters seen in at least 80 % of the frames within
    ``fiducial_radius_nm`` of one place that move with the common drift are picked
    automatically; a frame's drift is their mean offset, averaged over ``smooth_frames``.

    Every other column is carried through unchanged (the pixel columns x, y included), and the
    drift removed is added as ``drift_x_nm``, ``drift_y_nm``, ``drift_z_nm`` (summed with any
    drift columns already there). ``attrs["drift"]`` says what was used.
    """
    check_choice("method", method, ("rcc", "fiducials"))
    segment_frames = check_int("segment_frames", segment_frames, minimum=1)
    smooth_frames = check_int("smooth_frames", smooth_frames, minimum=1)
    pixel_nm = check_positive("pixel_nm", pixel_nm)
    radius = check_positive("fiducial_radius_nm", fiducial_radius_nm)
    frames = positions(locs, ("frame", "x_nm", "y_nm"))["frame"].astype(np.int64)
    if frames.nunique() < 2:
        raise ValueError("Drift correction needs localizations in at least two frames.")
    first, n_frames = int(frames.min()), int(frames.max() - frames.min() + 1)
    if method == "rcc":
        drift, used = _rcc_drift(locs, first, n_frames, segment_frames, pixel_nm)
    else:
        drift, used = _fiducial_drift(locs, first, n_frames, radius, smooth_frames)
    drift = drift - drift[0]
    index = np.clip(locs["frame"].to_numpy().astype(np.int64) - first, 0, n_frames - 1)
    out = locs.copy()
    for axis, (column, name) in enumerate(
        zip(("x_nm", "y_nm", "z_nm"), DRIFT_COLUMNS, strict=True)
    ):
        removed = drift[index, axis]
        out[column] = locs[column] - removed
        out[name] = (locs[name] if name in locs else 0.0) + removed
    out.attrs["drift"] = {"method": method, **used}
    return out


def drift_figure(corrected: pd.DataFrame):
    """The drift removed against frame, x, y and z (a matplotlib figure)."""
    import matplotlib.pyplot as plt

    per_frame = corrected.groupby("frame")[list(DRIFT_COLUMNS)].first()
    fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True)
    for ax, column in zip(axes, DRIFT_COLUMNS, strict=True):
        ax.plot(per_frame.index, per_frame[column], lw=1)
        ax.set_ylabel(f"{column.split('_')[1]} drift (nm)")
    axes[-1].set_xlabel("frame")
    used = corrected.attrs.get("drift", {})
    title = ", ".join(f"{k} {v}" for k, v in used.items())
    axes[0].set_title(f"Drift removed ({title})" if title else "Drift removed")
    fig.tight_layout()
    return fig

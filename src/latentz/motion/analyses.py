"""Analyses of gear motion: centroid trajectory, play, planar fits, residual spectra, flexure.

These follow the paper's Figs. 6–7 and Supp. Figs. 15, 18–20:

- the centroid of the constellation in every frame, and the nominal orientation of each frame
  (``steps_per_rev`` per revolution) from the accumulated rotation about z;
- play: the radial, tangential and axial range of the centroid at each nominal orientation (Fig. 7);
- residuals of a plane fitted to the particles of each frame, and their correlation with the
  residuals of the rigid transforms (Supp. Fig. 18a–b);
- amplitude spectra of residual series (Supp. Fig. 18c–d);
- the rotational play out of the plane: the slope of each particle's largest z range at any
  nominal location against its distance from the centre of rotation (Supp. Fig. 20).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from latentz._shared.validate import check_array, check_columns, check_int, check_positive
from latentz.motion.rigid import (
    POSITION_COLUMNS,
    _centre,
    _fit_transitions,
    kabsch,
    tracks_to_array,
)

__all__ = [
    "nominal_orientation",
    "centroid_trajectory",
    "play",
    "planar_residuals",
    "residual_correlation",
    "residual_spectrum",
    "peak_period",
    "OutOfPlanePlay",
    "out_of_plane_play",
]


def nominal_orientation(motion: pd.DataFrame, *, steps_per_rev: int = 64) -> pd.DataFrame:
    """Accumulated rotation about z and the nominal orientation of every frame.

    The signed rotation of each transition is γ (positive when the axis points up, β < π/2);
    its running sum from the first frame, rounded to the nearest multiple of 2π/steps_per_rev,
    gives the nominal orientation index (0 … steps_per_rev − 1). Transitions with undefined
    motion count as no rotation.

    Returns
    -------
    DataFrame
        frame, angle (rad, accumulated), nominal (int).
    """
    check_columns("motion", motion, ("frame", "previous_frame", "gamma", "beta"))
    steps = check_int("steps_per_rev", steps_per_rev, minimum=1)
    signed = np.nan_to_num(motion["gamma"] * np.sign(np.cos(motion["beta"])))
    angle = np.concatenate([[0.0], np.cumsum(signed)])
    frames = np.concatenate([[motion["previous_frame"].iloc[0]], motion["frame"].to_numpy()])
    step = 2.0 * np.pi / steps
    nominal = np.mod(np.round(angle / step).astype(np.int64), steps)
    return pd.DataFrame({"frame": frames, "angle": angle, "nominal": nominal})


def centroid_trajectory(
    tracks: pd.DataFrame, motion: pd.DataFrame, *, steps_per_rev: int = 64
) -> pd.DataFrame:
    """Centroid of the constellation in every frame, with its nominal orientation.

    The reference constellation is the frame with the most particles; in every frame it is fitted
    (Kabsch) to the particles seen there and its centroid carried along, so missed detections do
    not shift the centroid (with every particle seen it equals their plain mean).

    Returns
    -------
    DataFrame
        frame, x_nm, y_nm, z_nm, angle, nominal.
    """
    frames, _, pos = tracks_to_array(tracks)
    seen = np.isfinite(pos).all(-1)
    ref = pos[int(seen.sum(1).argmax())]
    # Complete the reference: carry each particle it lacks in from the first frame that has it.
    to_ref, shift = kabsch(
        pos, np.broadcast_to(ref, pos.shape), weights=seen & seen[int(seen.sum(1).argmax())]
    )
    first = seen.argmax(axis=0)
    cols = np.arange(pos.shape[1])
    carried = np.einsum("pij,pj->pi", to_ref[first], pos[first, cols]) + shift[first]
    ref = np.where(np.isfinite(ref), ref, carried)
    ok = np.isfinite(ref).all(-1)
    rot, trans = kabsch(
        np.broadcast_to(np.where(ok[:, None], ref, 0.0), pos.shape), pos, weights=seen & ok
    )
    centroid = np.einsum("fij,j->fi", rot, ref[ok].mean(0)) + trans
    orient = nominal_orientation(motion, steps_per_rev=steps_per_rev).set_index("frame")
    table = pd.DataFrame(
        {"frame": frames, "x_nm": centroid[:, 0], "y_nm": centroid[:, 1], "z_nm": centroid[:, 2]}
    )
    return table.join(orient, on="frame")


def play(centroids: pd.DataFrame) -> pd.DataFrame:
    """Range of the centroid at each nominal orientation: radial, tangential and axial (Fig. 7).

    The radial direction of a nominal orientation points from the centre of the centroid's path
    (the mean of the cluster means) to that cluster's mean.

    Returns
    -------
    DataFrame
        nominal, theta (rad, direction of the cluster), n_visits, radial_range_nm,
        tangential_range_nm, axial_range_nm.
    """
    check_columns("centroids", centroids, ("nominal", *POSITION_COLUMNS))
    data = centroids.dropna(subset=list(POSITION_COLUMNS))
    means = data.groupby("nominal")[list(POSITION_COLUMNS)].mean()
    centre = means.mean().to_numpy()
    rows = []
    for nominal, group in data.groupby("nominal"):
        d = means.loc[nominal].to_numpy()[:2] - centre[:2]
        radial = d / np.hypot(*d)
        tangential = np.array([-radial[1], radial[0]])
        xy = group[["x_nm", "y_nm"]].to_numpy() - centre[:2]
        rows.append(
            {
                "nominal": nominal,
                "theta": float(np.arctan2(d[1], d[0])),
                "n_visits": len(group),
                "radial_range_nm": float(np.ptp(xy @ radial)),
                "tangential_range_nm": float(np.ptp(xy @ tangential)),
                "axial_range_nm": float(np.ptp(group["z_nm"])),
            }
        )
    return pd.DataFrame(rows)


def planar_residuals(tracks: pd.DataFrame) -> pd.DataFrame:
    """z residuals of a plane ``z = a + b x + c y`` fitted to the particles of each frame.

    Returns
    -------
    DataFrame
        frame, particle, res_z_nm (the RMS per frame is ``groupby("frame")`` of its square).
    """
    frames, particles, pos = tracks_to_array(tracks)
    seen = np.isfinite(pos).all(-1)
    if (seen.sum(1) < 3).any():
        raise ValueError("Every frame needs at least 3 particles for a planar fit.")
    filled = np.where(seen[..., None], pos, 0.0)
    centre = filled.sum(1) / seen.sum(1)[:, None]
    local = np.where(seen[..., None], pos - centre[:, None, :], 0.0)
    design = np.concatenate([seen[..., None].astype(float), local[..., :2]], axis=2)
    normal = np.matmul(np.swapaxes(design, 1, 2), design)
    rhs = np.einsum("fpk,fp->fk", design, local[..., 2])
    coef = np.linalg.solve(normal, rhs[..., None])[..., 0]
    res = local[..., 2] - np.einsum("fpk,fk->fp", design, coef)
    f_idx, p_idx = np.nonzero(seen)
    return pd.DataFrame(
        {"frame": frames[f_idx], "particle": particles[p_idx], "res_z_nm": res[f_idx, p_idx]}
    )


def residual_correlation(tracks: pd.DataFrame) -> pd.DataFrame:
    """Per-particle correlation of rigid-transform and planar-fit z residuals (Supp. Fig. 18b).

    The rigid residual of a transition is paired with the planar residual of its later frame.

    Returns
    -------
    DataFrame
        particle, n, correlation (Pearson r).
    """
    frames, particles, pos = tracks_to_array(tracks)
    _, _, rigid, both = _fit_transitions(pos - _centre(tracks, None))
    planar = planar_residuals(tracks).set_index(["frame", "particle"])["res_z_nm"]
    rows = []
    for j, particle in enumerate(particles):
        sel = both[:, j]
        later = frames[1:][sel]
        plane = planar.reindex(pd.MultiIndex.from_arrays([later, np.full(later.size, particle)]))
        x, y = plane.to_numpy(), rigid[sel, j, 2]
        r = float(np.corrcoef(x, y)[0, 1]) if sel.sum() >= 3 else np.nan
        rows.append({"particle": particle, "n": int(sel.sum()), "correlation": r})
    return pd.DataFrame(rows)


def residual_spectrum(
    frames: np.ndarray, values: np.ndarray, *, oversample: int = 8
) -> pd.DataFrame:
    """Amplitude spectrum of a residual series sampled at (possibly gappy) integer frames.

    A direct Fourier sum on a frequency grid ``oversample`` times finer than the Rayleigh spacing
    ``1/T`` (``T`` the span in frames), from ``1/T`` to the Nyquist 0.5 per frame; the mean is
    removed. The amplitude of a sinusoid of amplitude ``A`` at a grid frequency is ``A``.

    Returns
    -------
    DataFrame
        frequency (per frame), period_cycles, amplitude (units of ``values``).
    """
    t = check_array("frames", frames, ndim=1).astype(float)
    v = check_array("values", values, ndim=1).astype(float)
    if t.shape != v.shape:
        raise ValueError(
            f"Expected `frames` and `values` of equal length, got {t.size} and {v.size}."
        )
    oversample = check_int("oversample", oversample, minimum=1)
    ok = np.isfinite(v)
    t, v = t[ok], v[ok] - v[ok].mean()
    span = np.ptp(t) + 1.0
    if t.size < 4:
        raise ValueError(f"Expected at least 4 finite values, got {t.size}.")
    freq = np.arange(1.0 / span, 0.5 + 1e-12, 1.0 / (oversample * span))
    amp = np.empty(freq.size)
    for start in range(0, freq.size, 512):
        f = freq[start : start + 512]
        phase = np.exp(-2j * np.pi * np.outer(f, t))
        amp[start : start + 512] = 2.0 * np.abs(phase @ v) / t.size
    return pd.DataFrame({"frequency": freq, "period_cycles": 1.0 / freq, "amplitude": amp})


def peak_period(
    spectrum: pd.DataFrame, *, min_period: float = 2.0, max_period: float = np.inf
) -> float:
    """Period (cycles) of the largest amplitude within [min_period, max_period], refined by a
    parabola through the peak and its neighbours in frequency."""
    check_columns("spectrum", spectrum, ("frequency", "amplitude"))
    lo = check_positive("min_period", min_period)
    sel = spectrum[(spectrum["period_cycles"] >= lo) & (spectrum["period_cycles"] <= max_period)]
    if len(sel) < 3:
        raise ValueError("Fewer than 3 spectrum points lie in [min_period, max_period].")
    f, a = sel["frequency"].to_numpy(), sel["amplitude"].to_numpy()
    k = int(np.clip(a.argmax(), 1, a.size - 2))
    denom = a[k - 1] - 2 * a[k] + a[k + 1]
    shift = 0.5 * (a[k - 1] - a[k + 1]) / denom if denom < 0 else 0.0
    return float(1.0 / (f[k] + np.clip(shift, -1, 1) * (f[k + 1] - f[k])))


@dataclass(frozen=True)
class OutOfPlanePlay:
    """Rotational play out of the plane (Supp. Fig. 20).

    ``particles`` has particle, distance_nm (mean distance from the centre of rotation in the
    plane), max_z_range_nm (largest z range over the nominal locations) and n_locations; the
    line ``max_z_range = intercept_nm + slope_rad × distance`` is fitted by least squares, with
    ``slope_err_rad`` its standard error from the scatter.
    """

    particles: pd.DataFrame
    slope_rad: float
    slope_err_rad: float
    intercept_nm: float


def out_of_plane_play(
    tracks: pd.DataFrame, motion: pd.DataFrame, *, steps_per_rev: int = 64, min_visits: int = 2
) -> OutOfPlanePlay:
    """Rotational play out of the plane from each particle's z range at the nominal locations.

    Parameters
    ----------
    tracks : DataFrame
        Linked localizations.
    motion : DataFrame
        :func:`latentz.motion.rigid_motion` of ``tracks`` (for the nominal orientations and the
        centre of rotation).
    steps_per_rev : int
        Nominal orientations per revolution.
    min_visits : int
        Nominal locations visited fewer times by a particle are skipped.
    """
    min_visits = check_int("min_visits", min_visits, minimum=2)
    orient = nominal_orientation(motion, steps_per_rev=steps_per_rev)
    data = tracks.merge(orient[["frame", "nominal"]], on="frame", how="inner")
    centre = _centre(tracks, motion.attrs.get("centre_nm"))
    data = data.assign(r_nm=np.hypot(data["x_nm"] - centre[0], data["y_nm"] - centre[1]))
    per_location = data.groupby(["particle", "nominal"])["z_nm"].agg(["max", "min", "size"])
    per_location = per_location[per_location["size"] >= min_visits]
    ranges = (per_location["max"] - per_location["min"]).groupby(level="particle")
    table = pd.DataFrame(
        {
            "distance_nm": data.groupby("particle")["r_nm"].mean(),
            "max_z_range_nm": ranges.max(),
            "n_locations": ranges.size(),
        }
    ).dropna()
    if len(table) < 4:
        raise ValueError("Fewer than 4 particles revisit a nominal location; cannot fit a slope.")
    coef, cov = np.polyfit(table["distance_nm"], table["max_z_range_nm"], 1, cov=True)
    return OutOfPlanePlay(
        particles=table.reset_index(),
        slope_rad=float(coef[0]),
        slope_err_rad=float(np.sqrt(cov[0, 0])),
        intercept_nm=float(coef[1]),
    )

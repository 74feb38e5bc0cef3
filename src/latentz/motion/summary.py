"""Drift and the Table-1 summary of motion in six degrees of freedom (paper, Table 1, Supp. Note 2).

Unintentional motion of the microscope moves every particle alike, so it looks like a translation
of the body. The paper estimates it from the apparent translation of the constellation centroid
while the gear does not move, and adds it in quadrature to the translation uncertainties (not to
the rotations, which common-mode motion does not affect).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pandas as pd

from latentz._shared.validate import check_columns
from latentz.motion.rigid import DOF_COLUMNS, tracks_to_array

__all__ = ["drift", "table1", "DOF_UNITS"]

#: Unit of each degree of freedom in the motion tables.
DOF_UNITS = {
    "gamma": "rad",
    "beta": "rad",
    "alpha": "rad",
    "dx_nm": "nm",
    "dy_nm": "nm",
    "dz_nm": "nm",
}
_TRANSLATIONS = ("dx_nm", "dy_nm", "dz_nm")


def drift(tracks: pd.DataFrame, *, frames: Iterable[int] | None = None) -> pd.Series:
    """Drift uncertainty from a static segment: the RMS apparent centroid translation per frame.

    Parameters
    ----------
    tracks : DataFrame
        Linked localizations (frame, particle, x_nm, y_nm, z_nm) recorded without intentional
        motion of the body.
    frames : iterable of int, optional
        Restrict to these frames (a static segment of a longer movie).

    Returns
    -------
    Series
        dx_nm, dy_nm, dz_nm: root mean square over consecutive frame pairs of the mean
        displacement of the particles seen in both frames. ``attrs["n_pairs"]`` is the number of
        pairs used.
    """
    check_columns("tracks", tracks, ("frame", "particle"))
    if frames is not None:
        wanted = np.asarray(list(frames))
        tracks = tracks[tracks["frame"].isin(wanted)]
    _, _, pos = tracks_to_array(tracks)
    if pos.shape[0] < 2:
        raise ValueError(f"Expected a static segment of at least 2 frames, got {pos.shape[0]}.")
    step = pos[1:] - pos[:-1]
    both = np.isfinite(step).all(-1)
    count = both.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        # NaN where no particle is seen in both frames
        shift = np.where(both[..., None], step, 0.0).sum(axis=1) / count[:, None]
    ok = np.isfinite(shift).all(axis=1)
    if not ok.any():
        raise ValueError("No pair of consecutive frames shares a particle in `tracks`.")
    rms = np.sqrt(np.mean(shift[ok] ** 2, axis=0))
    result = pd.Series(rms, index=list(_TRANSLATIONS), name="drift")
    result.attrs["n_pairs"] = int(ok.sum())
    return result


def table1(
    motion: pd.DataFrame, uncertainty: pd.DataFrame, *, drift_nm: pd.Series | None = None
) -> pd.DataFrame:
    """Summary of the motion in the form of the paper's Table 1.

    Parameters
    ----------
    motion : DataFrame
        From :func:`latentz.motion.rigid_motion`.
    uncertainty : DataFrame
        From :func:`latentz.motion.motion_uncertainty` (its ``sigma`` column is the localization
        component).
    drift_nm : Series, optional
        From :func:`drift`; added in quadrature to the translations.

    Returns
    -------
    DataFrame
        Indexed by degree of freedom: unit, mean, total_range (max − min), localization, drift
        (NaN for rotations or without ``drift_nm``), total.
    """
    check_columns("motion", motion, DOF_COLUMNS)
    if "sigma" not in getattr(uncertainty, "columns", ()):
        raise ValueError("`uncertainty` must be the table of motion_uncertainty (column sigma).")
    missing = [d for d in DOF_COLUMNS if d not in uncertainty.index]
    if missing:
        raise ValueError(f"`uncertainty` lacks degree(s) of freedom {', '.join(missing)}.")
    values = motion[list(DOF_COLUMNS)].to_numpy(float)
    local = uncertainty.loc[list(DOF_COLUMNS), "sigma"].to_numpy(float)
    drifts = np.full(len(DOF_COLUMNS), np.nan)
    if drift_nm is not None:
        for i, dof in enumerate(DOF_COLUMNS):
            if dof in _TRANSLATIONS:
                drifts[i] = float(drift_nm[dof])
    total = np.sqrt(local**2 + np.nan_to_num(drifts) ** 2)
    return pd.DataFrame(
        {
            "unit": [DOF_UNITS[d] for d in DOF_COLUMNS],
            "mean": np.nanmean(values, axis=0),
            "total_range": np.nanmax(values, axis=0) - np.nanmin(values, axis=0),
            "localization": local,
            "drift": drifts,
            "total": total,
        },
        index=pd.Index(DOF_COLUMNS, name="dof"),
    )

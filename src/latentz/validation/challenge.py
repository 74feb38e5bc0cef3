"""Scoring as the SMLM 2016 challenge scores 3D localizations: matching, Jaccard, RMSE, efficiency.

In every frame, localizations and true emitters are paired one-to-one: a pair is admissible when
it lies within ``lateral_nm`` laterally *and* ``axial_nm`` axially; among admissible pairings
the one with the most pairs is kept, and among those the smallest total lateral distance
(an assignment problem, :func:`match_frame`). Matched pairs are true positives, unmatched
localizations false positives, unmatched emitters false negatives, over all frames:

- Jaccard index, percent: ``J = 100 TP / (TP + FP + FN)``;
- lateral RMSE ``sqrt(mean(dx² + dy²))`` and axial RMSE ``sqrt(mean(dz²))`` over the pairs, nm;
- efficiency, percent: ``E = 100 − sqrt((100 − J)² + (α RMSE)²)``, with α = 1 nm⁻¹ laterally and
  0.5 nm⁻¹ axially; ``E_3D`` is the mean of the lateral and the axial efficiency.

E is 100 for a perfect result and falls without bound (it is negative when the errors are large).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from latentz._shared.validate import check_positive

__all__ = [
    "ALPHA_AXIAL_PER_NM",
    "ALPHA_LATERAL_PER_NM",
    "challenge_score",
    "correct_rows",
    "offset_pairs",
    "efficiency",
    "match_frame",
    "match_frames",
]

#: The challenge's weights of the RMSE in the efficiency, per nm.
ALPHA_LATERAL_PER_NM = 1.0
ALPHA_AXIAL_PER_NM = 0.5
_COLUMNS = ("frame", "x_nm", "y_nm", "z_nm")


def efficiency(jaccard_pct: float, rmse_nm: float, alpha_per_nm: float) -> float:
    """The challenge's efficiency, percent: ``100 − sqrt((100 − J)² + (α RMSE)²)``.

    >>> efficiency(100.0, 0.0, 1.0)
    100.0
    >>> efficiency(70.0, 40.0, 1.0)  # sqrt(30² + 40²) = 50
    50.0
    """
    return float(100.0 - np.hypot(100.0 - jaccard_pct, alpha_per_nm * rmse_nm))


def match_frame(
    truth_xyz_nm: np.ndarray,
    locs_xyz_nm: np.ndarray,
    *,
    lateral_nm: float = 250.0,
    axial_nm: float = 500.0,
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs between the true emitters and the localizations of one frame.

    Parameters
    ----------
    truth_xyz_nm, locs_xyz_nm : ndarray (n, 3), (m, 3)
        x, y, z in nm.
    lateral_nm, axial_nm : float
        A pair is admissible when its lateral distance is at most ``lateral_nm`` and its axial
        distance at most ``axial_nm``.

    Returns
    -------
    (truth_index, locs_index) : two int arrays of equal length
        The most admissible pairs, and among those the smallest summed lateral distance.
    """
    t = np.asarray(truth_xyz_nm, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(locs_xyz_nm, dtype=np.float64).reshape(-1, 3)
    if len(t) == 0 or len(m) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lateral = np.hypot(t[:, None, 0] - m[None, :, 0], t[:, None, 1] - m[None, :, 1])
    axial = np.abs(t[:, None, 2] - m[None, :, 2])
    ok = (lateral <= lateral_nm) & (axial <= axial_nm)
    # A forbidden pair costs more than every admissible pair together, so that the assignment
    # first maximises the number of admissible pairs, then minimises their summed distance.
    forbidden = lateral_nm * (min(t.shape[0], m.shape[0]) + 1) + 1.0
    cost = np.where(ok, lateral, forbidden)
    rows, cols = linear_sum_assignment(cost)
    keep = ok[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


def match_frames(
    truth: pd.DataFrame,
    locs: pd.DataFrame,
    *,
    lateral_nm: float = 250.0,
    axial_nm: float = 500.0,
) -> pd.DataFrame:
    """Pairs of every frame (:func:`match_frame`): one row per pair with ``frame``, the row
    labels ``truth_row`` and ``locs_row``, and the errors ``dx_nm``, ``dy_nm``, ``dz_nm``
    (localization − truth). Both tables need ``frame``, ``x_nm``, ``y_nm``, ``z_nm``; rows of
    ``locs`` with a non-finite coordinate count as localizations that match nothing."""
    lateral_nm = check_positive("lateral_nm", lateral_nm)
    axial_nm = check_positive("axial_nm", axial_nm)
    for name, table in (("truth", truth), ("locs", locs)):
        missing = [c for c in _COLUMNS if c not in table.columns]
        if missing:
            raise ValueError(
                f"Expected `{name}` to have the columns {list(_COLUMNS)}; missing: {missing}."
            )
    finite = np.isfinite(locs[list(_COLUMNS[1:])].to_numpy(np.float64)).all(axis=1)
    by_frame = dict(tuple(locs[finite].groupby("frame")))
    rows = []
    for frame, t in truth.groupby("frame"):
        m = by_frame.get(frame)
        if m is None:
            continue
        txyz = t[list(_COLUMNS[1:])].to_numpy(np.float64)
        mxyz = m[list(_COLUMNS[1:])].to_numpy(np.float64)
        ti, mi = match_frame(txyz, mxyz, lateral_nm=lateral_nm, axial_nm=axial_nm)
        d = mxyz[mi] - txyz[ti]
        rows.append(
            pd.DataFrame(
                {
                    "frame": frame,
                    "truth_row": t.index[ti],
                    "locs_row": m.index[mi],
                    "dx_nm": d[:, 0],
                    "dy_nm": d[:, 1],
                    "dz_nm": d[:, 2],
                }
            )
        )
    columns = ["frame", "truth_row", "locs_row", "dx_nm", "dy_nm", "dz_nm"]
    return pd.concat(rows, ignore_index=True) if rows else pd.DataFrame(columns=columns)


def challenge_score(
    truth: pd.DataFrame,
    locs: pd.DataFrame,
    *,
    lateral_nm: float = 250.0,
    axial_nm: float = 500.0,
) -> dict[str, float]:
    """The challenge's metrics of ``locs`` against ``truth`` (see the module docstring).

    Returns a dict: ``n_truth``, ``n_locs``, ``tp``, ``fp``, ``fn``, ``jaccard_pct``,
    ``rmse_lateral_nm``, ``rmse_axial_nm``, ``e_lateral``, ``e_axial``, ``e_3d`` (percent), and
    the mean errors ``bias_x_nm``, ``bias_y_nm``, ``bias_z_nm`` (NaN where nothing matched).
    """
    pairs = match_frames(truth, locs, lateral_nm=lateral_nm, axial_nm=axial_nm)
    tp = len(pairs)
    n_locs = int(np.isfinite(locs[list(_COLUMNS[1:])].to_numpy(np.float64)).all(axis=1).sum())
    fp, fn = n_locs - tp, len(truth) - tp
    jaccard = 100.0 * tp / (tp + fp + fn) if tp + fp + fn else float("nan")
    if tp:
        dx, dy, dz = (pairs[c].to_numpy(np.float64) for c in ("dx_nm", "dy_nm", "dz_nm"))
        rmse_lat = float(np.sqrt(np.mean(dx**2 + dy**2)))
        rmse_ax = float(np.sqrt(np.mean(dz**2)))
        bias = (float(dx.mean()), float(dy.mean()), float(dz.mean()))
    else:
        rmse_lat = rmse_ax = float("nan")
        bias = (float("nan"),) * 3
    e_lat = efficiency(jaccard, rmse_lat, ALPHA_LATERAL_PER_NM)
    e_ax = efficiency(jaccard, rmse_ax, ALPHA_AXIAL_PER_NM)
    return {
        "n_truth": len(truth),
        "n_locs": n_locs,
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "jaccard_pct": jaccard,
        "rmse_lateral_nm": rmse_lat,
        "rmse_axial_nm": rmse_ax,
        "e_lateral": e_lat,
        "e_axial": e_ax,
        "e_3d": 0.5 * (e_lat + e_ax),
        "bias_x_nm": bias[0],
        "bias_y_nm": bias[1],
        "bias_z_nm": bias[2],
    }


def offset_pairs(
    truth: pd.DataFrame,
    locs: pd.DataFrame,
    *,
    lateral_nm: float = 250.0,
    axial_nm: float = 500.0,
) -> tuple[pd.DataFrame, float]:
    """The pairs of :func:`match_frames` after one z offset is removed, and that offset (nm).

    As the challenge scores 3D data, the offset is the median axial error of the pairs matched
    within ``lateral_nm`` at any depth (the calibration's z = 0 and the truth's focal plane need
    not agree); then pairs are matched within ``lateral_nm`` laterally and ``axial_nm``
    axially, and their ``dz_nm`` is after the offset."""
    loose = match_frames(truth, locs, lateral_nm=lateral_nm, axial_nm=1e6)
    offset = float(np.median(loose["dz_nm"])) if len(loose) else 0.0
    shifted = locs.assign(z_nm=locs["z_nm"] - offset)
    return match_frames(truth, shifted, lateral_nm=lateral_nm, axial_nm=axial_nm), offset


def correct_rows(
    truth: pd.DataFrame,
    locs: pd.DataFrame,
    *,
    lateral_nm: float = 250.0,
    axial_nm: float = 500.0,
) -> tuple[np.ndarray, float]:
    """Which rows of ``locs`` are correct, paired with a true emitter by :func:`offset_pairs`,
    and the z offset removed (nm)."""
    pairs, offset = offset_pairs(truth, locs, lateral_nm=lateral_nm, axial_nm=axial_nm)
    correct = np.zeros(len(locs), bool)
    correct[locs.index.get_indexer(pairs["locs_row"])] = True
    return correct, offset

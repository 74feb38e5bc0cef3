"""One quality verdict per spot: the ``good`` column and the flags that explain it.

`localize` calls :func:`assess`, and `track`/the report read ``good``; the only other
verdict is :func:`latentz.localization.mismatch.check_calibration_fits`, which marks every spot
``inconsistent`` (not good) when the table as a whole contradicts the calibration. A spot is
good when it

- ``converged`` (the fit's own flag);
- is not a ``duplicate``: detections whose fits converge within :data:`DUPLICATE_PX` of each
  other in the same frame are one emitter; the fit with the smallest position error is kept;
- is not ``unresolved``: no other emitter's fitted centre lies within :data:`UNRESOLVED_PX`
  of it (in x and in y), where its light biases the fit beyond the challenge's tolerance (the
  two emitters of one two-emitter fit, the same ``pair``, were fitted together and do not
  count), and it is not ``merged``: an overlap the two-emitter fit could not resolve
  (:mod:`latentz.localization.pairs`);

and, with a calibration,

- is not ``out_of_range``: the calibration located it (``in_range``) and its z is likely
  within :data:`AXIAL_TOLERANCE_NM` of the truth: ``z_far_p``, the chance that it is not, at
  most :data:`FAR_LIMIT`. ``z_far_p`` takes the z error as normal with σ = ``z_err_nm``,
  restricted to where a spot in range can lie (its particle's calibrated range,
  :meth:`~latentz.calibration.Calibration.in_range_window`): in an unbounded range the limit
  is σ_z = 500 nm, while a spot whose range holds its error is located however wide σ_z;
- is not ``inconsistent``: its widths and ρ lie near the calibration curves at its estimated z.
  ``consistency_chi2`` is ``Σ ((v − v_cal(z)) / σ)²`` over v = wx, wy, ρ, where σ combines the
  spot's Cramér–Rao error, the calibration curve's scatter and :data:`CURVE_SCATTER` (a
  molecule's image is not quite the calibration bead's); it is compared with
  :data:`CHI2_LIMIT`. The amplitude is not compared: single molecules' brightness is unknown.

The thresholds are measured against truth (``benchmarks/bench_verdicts.py``: simulated molecules
of 300–10,000 photons at 0.2–2 per µm² on random astigmatic microscopes, each calibrated on its
own simulated beads): each flag alone removes at most about 2 % of the localizations that the
challenge's matching calls correct.

``width_ratio`` (observed over calibrated mean width) and ``axis_mismatch`` (ellipticity
across the calibration's astigmatism axis) say how each spot differs from the curves; whether
the calibration fits the table as a whole is measured by :mod:`latentz.localization.mismatch`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree
from scipy.special import ndtr

from latentz._shared.columns import with_columns

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = [
    "assess",
    "calibration_flags",
    "consistency",
    "curve_share2",
    "curve_spread",
    "summary",
    "good_rows",
    "QUALITY_COLUMNS",
    "FLAGS",
    "CHI2_LIMIT",
    "DUPLICATE_PX",
    "UNRESOLVED_PX",
    "AXIAL_TOLERANCE_NM",
    "FAR_LIMIT",
    "far_probability",
]

#: Fits in one frame closer than this (pixels) are the same emitter.
DUPLICATE_PX = 1.0
#: Fits closer than this in x and in y (pixels) bias each other: the distance at which the flag
#: loses 1.9 % of the correct localizations (2.4 % at 3.5 px, 3.0 % at 4) and removes 9 % of the
#: wrong ones (benchmarks/bench_verdicts.py).
UNRESOLVED_PX = 3.0
#: Consistency χ² above which a spot is inconsistent: the 98th percentile of correct
#: localizations' (benchmarks/bench_verdicts.py); far above χ²(2)'s 99.9 % point (13.8), since
#: a neighbour's light and the bead-molecule difference make real misfits heavy-tailed.
CHI2_LIMIT = 200.0
#: Relative difference between a molecule's widths and the calibration curves that is not in
#: their fit errors (the bead's size, the ROI's placement, pixel phase, field variation).
CURVE_SCATTER = 0.10
#: The challenge's axial tolerance (nm): a localization farther than this in z is not correct.
AXIAL_TOLERANCE_NM = 500.0
#: A spot whose z lies beyond AXIAL_TOLERANCE_NM of the truth with more than this chance is not
#: located: a normal error's share beyond 1σ (so σ_z ≤ 500 nm where the range is unbounded; the
#: tolerance holds z's 1σ interval). Against truth, on the 20 right calibrations of
#: benchmarks/bench_wrong_calibration.py (very weak, 3-8 nm RMS: seeds 13, 52, 113, 213, 313,
#: 413, 513, 613, 1013, 1113, 1213, 1313, 1513, 2213, 2613, 2713; weak 12, 112; strong 11, 111)
#: σ_z does not find the located spots that lie beyond: all 83 have ``z_far_p`` ≤ 0.27 (61 below
#: 0.01). The 2σ share (4.55 %) caught 4 of them and dropped 54 of the 4,772 correct located
#: spots, up to 7 % of one microscope's (seed 513; 2.5 % on 1313); this limit drops none.
FAR_LIMIT = 2 * float(ndtr(-1.0))
#: Flags that make a spot not good, in the order they are reported.
FLAGS = ("not_converged", "duplicate", "unresolved", "out_of_range", "inconsistent")
#: Columns :func:`assess` adds (without a calibration, only the first three and ``good``).
QUALITY_COLUMNS = (
    "duplicate",
    "unresolved",
    "out_of_range",
    "inconsistent",
    "consistency_chi2",
    "width_ratio",
    "axis_mismatch",
    "z_far_p",
    "good",
)


def _duplicates_and_neighbours(spots: pd.DataFrame) -> tuple[np.ndarray, ...]:
    """(duplicate, unresolved) flags, frame by frame; the rows of one two-emitter fit (the same
    ``pair`` number) are not each other's neighbours, and ``merged`` rows are unresolved."""
    n = len(spots)
    duplicate, unresolved = np.zeros(n, bool), np.zeros(n, bool)
    x, y = spots["x"].to_numpy(float), spots["y"].to_numpy(float)
    ok = spots["converged"].to_numpy(bool) & np.isfinite(x) & np.isfinite(y)
    error = np.hypot(spots["x_err"].to_numpy(float), spots["y_err"].to_numpy(float))
    error = np.where(np.isfinite(error), error, np.inf)
    frames = spots["frame"].to_numpy()
    pair = spots["pair"].to_numpy(np.int64) if "pair" in spots else np.full(n, -1)
    merged = spots["merged"].to_numpy(bool) if "merged" in spots else np.zeros(n, bool)
    order = np.lexsort((error, frames))  # within a frame, the most precise fit first
    bounds = np.flatnonzero(np.diff(frames[order])) + 1
    for rows in np.split(order, bounds):
        rows = rows[ok[rows]]
        if rows.size < 2:
            continue
        points = np.column_stack([x[rows], y[rows]])
        tree = cKDTree(points)
        for i, j in sorted(tree.query_pairs(DUPLICATE_PX)):
            if not duplicate[rows[i]]:
                duplicate[rows[j]] = True
        unique = rows[~duplicate[rows]]
        points = np.column_stack([x[unique], y[unique]])
        pairs = unique[cKDTree(points).query_pairs(UNRESOLVED_PX, p=np.inf, output_type="ndarray")]
        # the two emitters of one two-emitter fit were fitted together: neither biases the other
        partners = (pair[pairs[:, 0]] >= 0) & (pair[pairs[:, 0]] == pair[pairs[:, 1]])
        unresolved[pairs[~partners].ravel()] = True
    return duplicate, unresolved | merged


def curve_spread(name: str, own: np.ndarray | float, curves: dict[str, np.ndarray]) -> np.ndarray:
    """σ of a spot's ``name`` (wx, wy in px, or ρ) about calibration ``curves``
    (:meth:`~latentz.calibration.Calibration.curves_at`): its own fit error ``own``, the curve's
    scatter and :data:`CURVE_SCATTER` of the curve's value (of 1 for ρ), in quadrature."""
    return np.sqrt(np.square(own) + curves[f"{name}_scatter"] ** 2 + curve_share2(name, curves))


def curve_share2(name: str, curves: dict[str, np.ndarray]) -> np.ndarray | float:
    """The square of :data:`CURVE_SCATTER` of ``curves``' ``name`` (of 1 for ρ): the part of
    :func:`curve_spread` that follows the curve's value."""
    scale = np.abs(curves[name]) if name != "rho" else 1.0
    return (CURVE_SCATTER * scale) ** 2


def consistency(spots: pd.DataFrame, cal: Calibration) -> dict[str, np.ndarray]:
    """χ², width ratio and axis mismatch of each spot against the calibration curves at its z
    (``z_nm`` on particle ``cal_particle``; NaN where z is)."""
    from latentz.calibration.shape import ellipticity

    n = len(spots)
    z = spots["z_nm"].to_numpy(float)
    p = spots["cal_particle"].to_numpy(int)
    located = np.isfinite(z)
    curves = cal.curves_at(p[located], z[located])
    chi2, ratio, mismatch = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    total = np.zeros(located.sum())
    for name in ("wx", "wy", "rho"):
        value = spots[name].to_numpy(float)[located]
        own = spots[f"{name}_err"].to_numpy(float)[located] if f"{name}_err" in spots else 0.0
        total += ((value - curves[name]) / curve_spread(name, own, curves)) ** 2
    chi2[located] = total
    wx, wy, rho = (spots[c].to_numpy(float)[located] for c in ("wx", "wy", "rho"))
    ratio[located] = (np.abs(wx) + np.abs(wy)) / (np.abs(curves["wx"]) + np.abs(curves["wy"]))
    theta = cal.local.theta if cal.local.theta is not None else np.pi / 4
    across = np.array([np.sin(2 * theta), -np.cos(2 * theta)])
    e_obs = np.stack(ellipticity(wx, wy, rho), axis=-1) @ across
    e_cal = np.stack(ellipticity(curves["wx"], curves["wy"], curves["rho"]), axis=-1) @ across
    mismatch[located] = np.abs(e_obs - e_cal)
    return {"consistency_chi2": chi2, "width_ratio": ratio, "axis_mismatch": mismatch}


def far_probability(spots: pd.DataFrame, calibration: Calibration) -> np.ndarray:
    """Chance (0–1) that each spot's true z lies more than :data:`AXIAL_TOLERANCE_NM` from its
    ``z_nm``: a normal error of σ = ``z_err_nm`` restricted to the z where a spot of its
    particle ``cal_particle`` in range can lie (:meth:`Calibration.in_range_window`, widened to
    ``z_nm``); NaN where z or a positive σ is missing."""
    z, sigma = spots["z_nm"].to_numpy(float), spots["z_err_nm"].to_numpy(float)
    with np.errstate(invalid="ignore"):
        located = np.isfinite(z) & (sigma > 0)
    z, sigma = z[located], sigma[located]
    window = calibration.in_range_window(spots["cal_particle"].to_numpy(int)[located], z)
    lo, hi = np.fmin(window[:, 0], z), np.fmax(window[:, 1], z)

    def mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The normal error's share between a and b (nm), 0 where b < a."""
        return np.fmax(ndtr((b - z) / sigma) - ndtr((a - z) / sigma), 0.0)

    far = mass(lo, z - AXIAL_TOLERANCE_NM) + mass(z + AXIAL_TOLERANCE_NM, hi)
    out = np.full(len(spots), np.nan)
    out[located] = far / mass(lo, hi)
    return out


def calibration_flags(spots: pd.DataFrame, calibration: Calibration) -> dict[str, np.ndarray]:
    """``out_of_range``, ``inconsistent`` and their scores of ``spots`` that ``calibration``
    was applied to (module docstring): each spot's own, whatever the other rows."""
    far = far_probability(spots, calibration)
    with np.errstate(invalid="ignore"):
        inside = spots["in_range"].to_numpy(bool) & (far <= FAR_LIMIT)
    scores = consistency(spots, calibration)
    with np.errstate(invalid="ignore"):
        inconsistent = scores["consistency_chi2"] > CHI2_LIMIT
    return {"out_of_range": ~inside, "inconsistent": inconsistent, **scores, "z_far_p": far}


def assess(spots: pd.DataFrame, calibration: Calibration | None = None) -> pd.DataFrame:
    """A copy of ``spots`` with the quality flags, ``good``, and (with a calibration that was
    applied to them) the consistency scores; see the module docstring."""
    out = spots.drop(columns=[c for c in QUALITY_COLUMNS if c in spots.columns])
    duplicate, unresolved = _duplicates_and_neighbours(out)
    new = {"duplicate": duplicate, "unresolved": unresolved}
    good = out["converged"].to_numpy(bool) & ~duplicate & ~unresolved
    if calibration is not None:
        new |= calibration_flags(out, calibration)
        good &= ~new["out_of_range"] & ~new["inconsistent"]
    return with_columns(out, new | {"good": good})


def summary(table: pd.DataFrame) -> dict[str, int]:
    """Count of rows, good rows, and rows not good by each flag (a row can carry several)."""
    counts = {"rows": len(table), "good": int(table["good"].sum())}
    if "converged" in table:
        counts["not_converged"] = int((~table["converged"].astype(bool)).sum())
    for flag in FLAGS[1:]:
        if flag in table:
            counts[flag] = int(table[flag].astype(bool).sum())
    return counts


def reasons(counts: dict[str, int]) -> str:
    """The flag counts of :func:`summary` that are not zero, as words: "duplicate 3, ..."."""
    return ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items() if k in FLAGS and v)


def good_rows(table: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """The good rows of a localization table and one line saying what was dropped and why
    (all rows, and an empty line, for a table without the ``good`` column)."""
    if "good" not in table.columns:
        return table, ""
    counts = summary(table)
    dropped = counts["rows"] - counts["good"]
    why = reasons(counts)
    line = f"used {counts['good']} good of {counts['rows']} localizations; dropped {dropped}"
    return table[table["good"].astype(bool)], line + (f" ({why})" if why else "")

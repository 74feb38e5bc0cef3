"""Close pairs: where one emitter's fit is shaped beyond one emitter, fit two and keep both.

Each detection is fitted with one Gaussian of eq. 1 (:mod:`latentz.localization.movie`). A fit
that is poor (Pearson chi-square :data:`CHI2_SDS` standard deviations above its degrees of
freedom; at the frame's edge, over the ROI's pixels inside the frame) is a candidate when

- two or more detections' fits converged on it (within `DUPLICATE_PX`, in one ROI centred on
  the same spot): the detector saw two peaks where one Gaussian sees one spot, an overlap of
  emitters about 1–2 px apart that one fit merges; or
- no other emitter's fit lies in its ROI, and it is shaped beyond what one emitter looks like:

  - with a calibration, the calibration does not locate it or its widths and ρ lie far from
    the curves at its z (``out_of_range`` or ``inconsistent`` of :mod:`.quality`);
  - without one, its long-axis width exceeds that of the chunk's isolated fits (no other
    emitter's fit in the ROI; a spot the detector saw twice counts once) by more than
    :data:`WIDTH_MADS` robust standard deviations (1.4826 MAD) above their median: nothing else
    says how wide one emitter is.

Without a calibration, a fit no wider than that is poor only beyond the misfit one emitter of
its brightness shows: its chi-square, and its pair's likelihood ratio, are divided by the
:func:`dispersion` that the chunk's isolated fits show at its brightness (a quasi-likelihood
test). A bright real PSF is no Gaussian: a bead of 30,000 photons 500 nm or more from focus is
fitted to 3–6 times the noise, the detector sees two peaks along the long spot, and a second
Gaussian raises the likelihood by 130–500, yet every single emitter there shows that much. Two
emitters blurred into one spot wider than one emitter are a candidate on their width, their
chi-square read against the noise: their sum is often closer to a Gaussian than one real PSF.

With a calibration, a poor fit is no candidate where it looks like one emitter beyond the
calibrated range: read over all the calibration's planes it lies beyond the range, and its
widths and ρ are consistent with the curves there (``consistency_chi2`` of :mod:`.quality` at
most χ²(2)'s 99th percentile). Far from focus a real PSF is a ring wider than the ROI, which
one Gaussian fits poorly and two fit better (its bright centre and the rest), yet the
calibration's own particles look like it there. Such a spot stays one row, with the flags it
has (``out_of_range`` or ``inconsistent``).

Candidates get the two-emitter fit of :mod:`latentz.fit.pairs`, once per spot. Its two emitters
replace the one-emitter row, and every other fit that converged on the same spot, when the second
emitter is significant (:func:`latentz.fit.pairs.is_split`) and each looks like one emitter (located
and consistent with the calibration, and no farther from its curves than the one-emitter fit by
more than :data:`CHI2_WORSE`; or no wider than that limit), unless either lies on another
detection's fit (a neighbour detected by itself) or outside the frame. Both rows carry the same
``pair`` number. A candidate that is not split stays as it was: an overlap the two-emitter fit
cannot resolve. Fits that converged on one spot remain one emitter, which :func:`.quality.assess`
reports once (the others are ``duplicate``). A candidate shaped beyond one emitter is, without a
calibration, marked ``merged``, which :func:`.quality.assess` flags ``unresolved``; with one, it is
already ``out_of_range`` or ``inconsistent``, the flags that made it a candidate (and that dim or
distant single emitters carry too, so ``unresolved`` is not added). Only candidates are fitted
twice, so ordinary spots cost nothing more.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numba
import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from latentz.calibration.readout import CHI2_HELD
from latentz.fit._model import PARAMS, photons_of
from latentz.fit.api import CORRELATION_COLUMNS, ERROR_COLUMNS
from latentz.fit.pairs import PairFit, fit_pairs, is_split
from latentz.localization.quality import DUPLICATE_PX, calibration_flags, consistency

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = [
    "split_pairs", "box_pairs", "copies", "crowded", "dispersion", "PAIR_COLUMNS",
    "WIDTH_MADS", "CHI2_SDS",
]  # fmt: skip

#: Columns :func:`split_pairs` adds: the pair number (−1 for a one-emitter row) and ``merged``.
PAIR_COLUMNS = ("pair", "merged")
#: Without a calibration, a fit whose long-axis width lies this many robust standard deviations
#: above the median of the chunk's isolated fits is wider than one emitter.
WIDTH_MADS = 5.0
#: With a calibration, a member of a two-emitter fit whose consistency χ² with the curves
#: (:mod:`.quality`) exceeds that of the one-emitter fit it would replace by more than this
#: (χ²(3)'s 99th percentile) fits the calibration worse than one emitter does: the split is not
#: kept (one defocused emitter, not Gaussian, seen as two peaks along its long axis).
CHI2_WORSE = 11.34
#: A one-emitter fit whose Pearson chi-square exceeds its degrees of freedom (pixels − 7) by
#: this many of its standard deviations fits poorly: only those can hold two emitters.
CHI2_SDS = 3.0


def long_axis_width(wx: np.ndarray, wy: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Standard deviation (pixels) along the long axis of eq. 1's ellipse."""
    mean, half = (wx**2 + wy**2) / 2, (wx**2 - wy**2) / 2
    return np.sqrt(mean + np.sqrt(half**2 + (rho * wx * wy) ** 2))


def _width(table: pd.DataFrame) -> np.ndarray:
    return long_axis_width(*(table[c].to_numpy(float) for c in ("wx", "wy", "rho")))


def _isolated(table: pd.DataFrame, group: np.ndarray, crowd: np.ndarray) -> np.ndarray:
    """Which rows are the isolated fits: converged, the first of their `copies` ``group`` (a
    spot the detector saw twice counts once), and not ``crowd`` (`crowded`: no other emitter's
    fit in the ROI)."""
    first = group == np.arange(len(table))
    return table["converged"].to_numpy(bool) & first & ~crowd


def _width_limit(table: pd.DataFrame, isolated: np.ndarray) -> float:
    """Long-axis width (pixels) beyond one emitter's, from the table's ``isolated`` fits: their
    median plus :data:`WIDTH_MADS` robust standard deviations (infinite with no such fit)."""
    width = _width(table)[isolated]
    width = width[np.isfinite(width)]
    if width.size == 0:
        return np.inf
    median = float(np.median(width))
    return median + WIDTH_MADS * 1.4826 * float(np.median(np.abs(width - median)))


def dispersion(
    table: pd.DataFrame, rois: np.ndarray, corner: np.ndarray, readnoise: float,
    isolated: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Per row, the Pearson chi-square over its degrees of freedom that one emitter of its fit's
    brightness and shape shows in these ROIs, 1 at least: ``1 + f² Σ s² / (mu + σ²) / dof``
    over the ROI's pixels inside the frame, with ``s`` the fit's counts above its background,
    ``mu`` with it, ``σ`` the read noise (photoelectrons). A real PSF departs from eq. 1 by about
    a fixed fraction of its signal in each pixel, whose mean square ``f²`` adds that sum to the
    chi-square; ``f²`` is the median over the ``isolated`` rows (most are one emitter) of their
    chi-square excess over the sum (0 at least, and with no such row). ``rois`` (n, h, w) and
    ``corner`` (n, 2, x and y) as :func:`split_pairs` takes them."""
    params = table[list(PARAMS)].to_numpy(float, copy=True)
    params[:, :2] -= corner
    weight = _signal_weights(params, rois, float(readnoise) ** 2)
    dof = np.maximum(np.isfinite(rois).sum(axis=(1, 2)) - len(PARAMS), 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        fraction = (table["chi2"].to_numpy(float) - dof) / weight
    usable = isolated & np.isfinite(fraction)
    f2 = max(float(np.median(fraction[usable])), 0.0) if usable.any() else 0.0
    return 1.0 + f2 * weight / dof


@numba.njit(parallel=True, nogil=True, cache=True)
def _signal_weights(params: np.ndarray, rois: np.ndarray, noise_sq: float) -> np.ndarray:
    """Per ROI, ``Σ s² / (mu + noise_sq)`` over its finite pixels: ``s`` eq. 1's counts above
    the background at the pixel centres for ``params`` ((n, 7), `PARAMS` in ROI pixels), ``mu``
    with it, ``noise_sq`` the read noise's variance (photoelectrons²)."""
    n, h, w = rois.shape
    out = np.zeros(n)
    for i in numba.prange(n):
        x, y, amp, bg, wx, wy, rho = params[i]
        om = 1.0 - rho * rho
        total = 0.0
        for r in range(h):
            v = (r - y) / wy
            for c in range(w):
                if np.isfinite(rois[i, r, c]):
                    u = (c - x) / wx
                    s = amp * np.exp(-0.5 * (u * (u - rho * v) + v * (v - rho * u)) / om)
                    total += s * s / max(s + bg + noise_sq, 1e-12)
        out[i] = total
    return out


def _beyond_one(table: pd.DataFrame, calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Which rows of ``table`` the calibration does not locate or finds its widths and ρ far
    from (``out_of_range`` or ``inconsistent``, :func:`.quality.calibration_flags`), and each
    row's ``consistency_chi2`` (NaN where not located)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # localize applies the calibration again, and warns there
        flags = calibration_flags(calibration.apply(table), calibration)
    return flags["out_of_range"] | flags["inconsistent"], flags["consistency_chi2"]


def _one_beyond_range(table: pd.DataFrame, calibration: Calibration) -> np.ndarray:
    """Which rows of ``table`` look like one emitter beyond the calibrated range: their
    wx, wy, ρ read outside it (:meth:`~latentz.calibration.Calibration.z_beyond_range`) are
    consistent with the curves there (``consistency_chi2`` of :mod:`.quality` at most
    :data:`~latentz.calibration.readout.CHI2_HELD`, χ²(2)'s 99th percentile)."""
    z, particle = calibration.z_beyond_range(table)
    rows = table.assign(z_nm=z, cal_particle=particle)
    with np.errstate(invalid="ignore"):
        return consistency(rows, calibration)["consistency_chi2"] <= CHI2_HELD


def crowded(table: pd.DataFrame, half: float) -> np.ndarray:
    """Which rows have another fit within ``half`` px (x and y; at least `DUPLICATE_PX`) that
    is not the same emitter (more than `DUPLICATE_PX` away): a third emitter the two-emitter
    fit would not model."""
    xy, frame = _xy(table), table["frame"].to_numpy()
    i, j = box_pairs(xy, frame, xy, frame, half)
    apart = np.hypot(*(xy[i] - xy[j]).T) > DUPLICATE_PX
    return np.bincount(i[apart], minlength=len(xy)) > 0


def box_pairs(
    a: np.ndarray, a_frame: np.ndarray, b: np.ndarray, b_frame: np.ndarray, half: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i, j) of points ``a[i]`` and ``b[j]`` ((n, 2) and (m, 2), x and y in px) of
    one frame within ``half`` px of each other in x and in y; points that are not finite have
    none. Found by sorting ``b`` on (frame, x): each point of ``a`` reads the run of ``b`` in
    its frame within ``half`` in x (``a``'s keys searched in ascending order), and keeps those
    within ``half`` in y too (`_within`). Pairs come in ``a``'s order, each point's in
    ``b``'s sorted order; no tree."""
    a_ok = np.flatnonzero(np.isfinite(a[:, 0]) & np.isfinite(a[:, 1]))
    b_ok = np.flatnonzero(np.isfinite(b[:, 0]) & np.isfinite(b[:, 1]))
    if a_ok.size == 0 or b_ok.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # one sort key: the frames laid end to end along x, each wider than its points and reach
    x0 = min(a[a_ok, 0].min(), b[b_ok, 0].min())
    width = max(a[a_ok, 0].max(), b[b_ok, 0].max()) - x0 + 2 * half + 2
    f0 = min(a_frame[a_ok].min(), b_frame[b_ok].min())
    key_b = (b_frame[b_ok] - f0) * width + (b[b_ok, 0] - x0)
    order = np.argsort(key_b, kind="stable")
    key_b, b_sorted = key_b[order], b_ok[order]
    key_a = (a_frame[a_ok] - f0) * width + (a[a_ok, 0] - x0)
    margin = half + 1.0  # more than the key's rounding; the exact test follows
    # each point's run of b within reach in x, searched with the queries in ascending order
    ascending = np.argsort(key_a)
    lo, hi = np.empty((2, key_a.size), np.int64)
    lo[ascending] = np.searchsorted(key_b, key_a[ascending] - margin, side="left")
    hi[ascending] = np.searchsorted(key_b, key_a[ascending] + margin, side="right")
    a, b = np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.float64)
    return _within(a, np.asarray(a_frame), a_ok, b, np.asarray(b_frame), b_sorted, lo, hi,
                   float(half))  # fmt: skip


@numba.njit(cache=True)
def _within(
    a: np.ndarray, a_frame: np.ndarray, a_ok: np.ndarray, b: np.ndarray, b_frame: np.ndarray,
    b_sorted: np.ndarray, lo: np.ndarray, hi: np.ndarray, half: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The pairs (i, j), ``i = a_ok[k]`` and ``j`` in ``b_sorted[lo[k]:hi[k]]``, of one frame
    and within ``half`` px in x and in y, in that order."""
    i = np.empty((hi - lo).sum(), np.int64)
    j = np.empty_like(i)
    n = 0
    for k in range(len(a_ok)):
        p = a_ok[k]
        for q in b_sorted[lo[k] : hi[k]]:
            if (a_frame[p] == b_frame[q] and abs(a[p, 0] - b[q, 0]) <= half
                    and abs(a[p, 1] - b[q, 1]) <= half):  # fmt: skip
                i[n] = p
                j[n] = q
                n += 1
    return i[:n], j[:n]


def copies(x: np.ndarray, y: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """For each fit (``x, y`` in pixels, ``frame``), the first of its group of fits of one frame
    within `DUPLICATE_PX` of each other (chained): detections whose fits converged on one spot
    share a group. A fit that is not finite is a group of its own."""
    n = len(x)
    xy = np.column_stack([x, y])
    i, j = box_pairs(xy, np.asarray(frame), xy, np.asarray(frame), DUPLICATE_PX)
    close = (i < j) & (np.hypot(*(xy[i] - xy[j]).T) <= DUPLICATE_PX)
    graph = coo_matrix((np.ones(close.sum()), (i[close], j[close])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return np.unique(label, return_index=True)[1][label]


def _candidates(
    table: pd.DataFrame,
    calibration: Calibration | None,
    limit: float,
    seen_pixels: np.ndarray,
    group: np.ndarray,
    spread: np.ndarray,
    crowd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(candidate, beyond, chi2): which rows, fitted in ROIs of which ``seen_pixels`` lie in
    the frame and not ``crowd`` (`crowded`: another emitter's fit in the ROI, which the
    two-emitter fit would not model), get the two-emitter fit (one per `copies` group), which
    are shaped beyond one emitter (see the module docstring), and their consistency χ² with
    the calibration (NaN without one, or where it does not locate them); a row's chi-square is
    read over its ``spread``, the `dispersion` one emitter shows. The calibration is applied to
    the poor fits only."""
    finite = np.isfinite(table[list(PARAMS)].to_numpy(float)).all(axis=1) & ~crowd
    dof = seen_pixels - len(PARAMS)  # a ROI clipped to the frame sees fewer pixels
    with np.errstate(invalid="ignore"):
        scaled = table["chi2"].to_numpy(float) / spread
        poor = finite & (scaled > dof + CHI2_SDS * np.sqrt(2 * dof))
    seen_twice = np.bincount(group, minlength=len(table))[group] > 1
    chi2 = np.full(len(table), np.nan)
    if calibration is None:
        with np.errstate(invalid="ignore"):
            beyond = poor & (_width(table) > limit)
    else:
        beyond = np.zeros(len(table), bool)
        if poor.any():
            beyond[poor], chi2[poor] = _beyond_one(table[poor], calibration)
            poor[poor] = ~_one_beyond_range(table[poor], calibration)
            beyond &= poor
    first = group == np.arange(len(table))
    return first & (beyond | (poor & seen_twice)), beyond, chi2


def _look_like_one(
    members: pd.DataFrame, calibration: Calibration | None, limit: float, chi2_one: np.ndarray
) -> np.ndarray:
    """Which member rows look like one emitter: located and consistent, and, with a calibration,
    their consistency χ² at most :data:`CHI2_WORSE` above ``chi2_one``, that of the one-emitter
    fit they would replace (member order; NaN: no such limit); without one, narrow enough."""
    if calibration is None:
        return _width(members) <= limit
    beyond, chi2 = _beyond_one(members, calibration)
    with np.errstate(invalid="ignore"):
        return ~beyond & ~(chi2 > chi2_one + CHI2_WORSE)


def _member_rows(rows: pd.DataFrame, fit: PairFit, corner: np.ndarray) -> pd.DataFrame:
    """Two rows per row of ``rows`` (emitter 0 then 1), in full-frame pixels (ROI corners
    ``corner``, (n, 2) as x, y), with the two-emitter fit's values, errors and correlations."""
    n = len(rows)
    members = rows.loc[rows.index.repeat(2)].reset_index(drop=True)
    params = fit.params.reshape(2 * n, len(PARAMS)).copy()
    params[:, :2] += np.repeat(corner, 2, axis=0)
    for k, name in enumerate(PARAMS):
        members[name] = params[:, k]
    members["photons"] = photons_of(params[:, 2], params[:, 4], params[:, 5], params[:, 6])
    errors = fit.errors.reshape(2 * n, len(PARAMS))
    for k, name in enumerate(ERROR_COLUMNS):
        members[name] = errors[:, k]
    correlations = fit.correlations.reshape(2 * n, len(CORRELATION_COLUMNS))
    for k, name in enumerate(CORRELATION_COLUMNS):
        members[name] = correlations[:, k]
    for name, values in (("loglik", fit.loglik), ("chi2", fit.chi2),
                         ("iterations", fit.iterations), ("converged", fit.converged)):  # fmt: skip
        members[name] = np.repeat(values, 2)
    return members


def split_pairs(
    table: pd.DataFrame,
    rois: np.ndarray,
    corner: np.ndarray,
    *,
    readnoise: float,
    calibration: Calibration | None = None,
) -> pd.DataFrame:
    """One chunk's one-emitter rows with each resolved close pair as two rows.

    Parameters
    ----------
    table : DataFrame
        One row per ROI: ``frame``, the columns of :func:`latentz.fit.fit_rois` in full-frame
        pixels, and any further columns (copied to both rows of a pair).
    rois : ndarray (n, h, w)
        The ROIs the rows were fitted in, photoelectrons.
    corner : ndarray (n, 2)
        Each ROI's first column and row in the frame (pixels).
    readnoise : float
        Read-noise standard deviation in photoelectrons.
    calibration : Calibration, optional
        Says what one emitter looks like; without it, the chunk's own fits do.

    Returns
    -------
    DataFrame
        ``table`` with `PAIR_COLUMNS`, rows ordered by frame (see the module docstring).
    """
    table = table.reset_index(drop=True).assign(pair=-1, merged=False)
    group = copies(*(table[c].to_numpy(float) for c in ("x", "y", "frame")))
    crowd = crowded(table, (min(rois.shape[1:]) - 1) / 2)
    isolated = _isolated(table, group, crowd)
    limit = _width_limit(table, isolated)
    seen = np.isfinite(rois).sum(axis=(1, 2))
    spread = np.ones(len(table))
    if calibration is None:  # one emitter's misfit, where the width does not show two
        with np.errstate(invalid="ignore"):
            narrow = ~(_width(table) > limit)
        spread[narrow] = dispersion(table, rois, corner, readnoise, isolated)[narrow]
    chosen, beyond, chi2 = _candidates(table, calibration, limit, seen, group, spread, crowd)
    candidates = np.flatnonzero(chosen)
    if candidates.size == 0:
        return table
    local = table.loc[candidates, list(PARAMS)].to_numpy(float, copy=True)
    local[:, :2] -= corner[candidates]
    fit = fit_pairs(rois[candidates], local, readnoise=readnoise, errors="sandwich")
    proposed = is_split(fit, rois.shape[1:], spread[candidates]) & _in_frame(fit, rois[candidates])
    # without a calibration the width is the evidence; with one, the flags that made a candidate
    table.loc[candidates, "merged"] = beyond[candidates] & (calibration is None)
    if not proposed.any():
        return table
    members = _member_rows(table.loc[candidates[proposed]], _take(fit, proposed),
                           corner[candidates[proposed]])  # fmt: skip
    members["pair"] = np.repeat(candidates[proposed], 2)
    members["merged"] = False
    members.attrs = table.attrs
    one = _look_like_one(members, calibration, limit, np.repeat(chi2[candidates[proposed]], 2))
    detected = _detected_apart(table, members, group)
    kept = one[0::2] & one[1::2] & ~detected
    table.loc[candidates[proposed][detected], "merged"] = False
    # the pair replaces its row and every other fit that converged on the same spot
    keep_rows = ~np.isin(group, candidates[proposed][kept])
    out = pd.concat([table[keep_rows], members[np.repeat(kept, 2)]], ignore_index=True)
    return out.sort_values("frame", kind="stable", ignore_index=True)


def _detected_apart(table: pd.DataFrame, members: pd.DataFrame, group: np.ndarray) -> np.ndarray:
    """For each pair of ``members`` (rows 2k, 2k + 1), whether either emitter is within
    `DUPLICATE_PX` of another detection's fit in its frame (not one of the `copies` ``group``
    of the pair's own row ``table.loc[pair]``): the ROI held a neighbour that was detected and
    fitted by itself."""
    if len(members) == 0:
        return np.zeros(0, bool)
    at, fits = _xy(members), _xy(table)
    i, j = box_pairs(at, members["frame"].to_numpy(), fits, table["frame"].to_numpy(),
                     DUPLICATE_PX)  # fmt: skip
    close = np.hypot(*(at[i] - fits[j]).T) <= DUPLICATE_PX
    i, j = i[close], j[close]
    own = group[members["pair"].to_numpy()]
    other = np.bincount(i[group[j] != own[i]], minlength=len(members)) > 0
    return other[0::2] | other[1::2]


def _in_frame(fit: PairFit, rois: np.ndarray) -> np.ndarray:
    """Whether both emitters of each fit lie on a pixel of their ROI inside the frame (not NaN)."""
    n, h, w = rois.shape
    x, y = (np.clip(np.rint(np.nan_to_num(fit.params[..., k])), 0, s - 1).astype(int)
            for k, s in ((0, w), (1, h)))  # fmt: skip
    return np.isfinite(rois[np.arange(n)[:, None], y, x]).all(axis=1)


def _xy(rows: pd.DataFrame) -> np.ndarray:
    """(n, 2) x, y (pixels) of a table's rows."""
    return np.column_stack([rows["x"].to_numpy(float), rows["y"].to_numpy(float)])


def _take(fit: PairFit, rows: np.ndarray) -> PairFit:
    return PairFit(*(field[rows] for field in fit))

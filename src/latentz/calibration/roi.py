"""The ROI size from the data: the candidate whose calibration localizes typical emitters best.

A larger ROI holds more of a defocused spot, so it measures farther from focus; it also holds
more background, more of a neighbour's light and more of a defocused ring, whose fitted width
then depends on the ring's structure rather than on z, so near focus it can cost precision.
No rule on the spots' own fitted widths settles this (the width of a ring grows with the ROI it
is fitted in, and such a rule runs away). The ROI is therefore chosen by what it is for:

1. **Candidates** (:func:`candidate_rois`): the smallest odd ROI that holds 95 % of an
   in-focus spot (:func:`roi_for_width` of the particles' narrowest width), then every
   :data:`ROI_STEP` pixels, :data:`N_CANDIDATES` in all, none larger than the images allow
   (:func:`roi_limit`) nor than the particles' spacing (:func:`spacing_limit`: at most a
   quarter of them with a neighbour inside their ROI).
2. **Score** (:func:`expected_errors`): each candidate is calibrated, and on every plane of the
   stack the expected z error of typical emitters is taken over its kept particles: the
   cross-validated error (each particle's images localized with the nearest *other*
   particle's inverse model, as :mod:`~latentz.calibration.shape_choice` does), in quadrature
   with the Cramér–Rao σ_z of an emitter of 10³ and of 10⁴ photons imaged like the particle in
   that ROI, and, for emitters like the calibration particles, the cross-validated error
   alone. Where a particle's plane is outside its usable range
   (:attr:`~latentz.calibration.Calibration.usable_planes`) the error is that of a guess
   anywhere in the stack (span/√12), as is any error above it.
3. **Choice** (:func:`choose_roi`): ``core_nm`` is the RMS of those errors over the *core*
   planes (where every candidate measures at least half its kept particles: near focus);
   ``range_nm`` the same over every plane any candidate measures. Candidates within
   :data:`CORE_TOLERANCE` of the best ``core_nm`` are eligible, and the one with the smallest
   ``range_nm`` among them is chosen (the smaller ROI on a tie). So a larger ROI that measures
   farther from focus is taken only where it costs nothing near focus, and a shorter usable z
   range is preferred to lost precision near focus. A candidate whose calibration fails is
   skipped, so the choice never fails where a smaller ROI works.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import erfinv

from latentz.calibration.dim_crossval import dim_held_out
from latentz.calibration.precision import crlb_sigma_z
from latentz.calibration.shape import uses_amplitude
from latentz.calibration.shape_choice import _cross_validated

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration
    from latentz.calibration.traces import Traces

__all__ = [
    "CORE_TOLERANCE",
    "EMITTER_PHOTONS",
    "HALF_WIDTH_PER_SIGMA",
    "MIN_ROI",
    "N_CANDIDATES",
    "PHOTON_FRACTION",
    "ROI_STEP",
    "candidate_rois",
    "choose_roi",
    "expected_errors",
    "focus_width_px",
    "roi_for_width",
    "roi_limit",
    "spacing_limit",
]

#: Fraction of an in-focus spot's photons the smallest candidate holds.
PHOTON_FRACTION = 0.95
#: k in ``h ≥ k w``: ``erf(k / √2)² = PHOTON_FRACTION`` (about 2.24).
HALF_WIDTH_PER_SIGMA = float(math.sqrt(2.0) * erfinv(math.sqrt(PHOTON_FRACTION)))
#: The smallest ROI a 7-parameter Gaussian fit is given (pixels).
MIN_ROI = 7
#: Pixels between candidate ROIs, and how many there are at most.
ROI_STEP = 4
N_CANDIDATES = 5
#: Most fraction of the particles allowed a neighbour inside their ROI (:func:`spacing_limit`).
CROWDED_FRACTION = 0.25
#: Photon counts of the typical single emitters the ROI is judged for.
EMITTER_PHOTONS = (1e3, 1e4)
#: A candidate whose near-focus error is within this fraction of the best is eligible.
CORE_TOLERANCE = 0.05


def roi_limit(image_shape: tuple[int, int]) -> int:
    """Largest odd ROI (pixels) that fits images of ``(rows, columns)`` with one pixel to spare
    on each side, so that a particle need not sit exactly at the centre to be detected."""
    side = int(min(image_shape)) - 2
    return side if side % 2 else side - 1


def roi_for_width(width_px: float) -> int:
    """Smallest odd ROI side (pixels, at least :data:`MIN_ROI`) that reaches
    ``HALF_WIDTH_PER_SIGMA`` spot widths ``width_px`` (pixels) from its centre each way, so that
    it holds :data:`PHOTON_FRACTION` of a Gaussian spot's photons."""
    if not np.isfinite(width_px) or width_px <= 0:
        raise ValueError(f"Expected a finite, positive spot width, got {width_px!r} px.")
    return max(MIN_ROI, 2 * math.ceil(HALF_WIDTH_PER_SIGMA * width_px - 0.5) + 1)


def focus_width_px(traces: Traces) -> float:
    """Median over the particles of their narrowest converged spot, as the geometric mean
    ``sqrt(wx wy)`` (pixels; astigmatism widens one axis where the other is narrowest); NaN
    if no fit converged."""
    width = np.sqrt(np.abs(traces["wx"] * traces["wy"]))
    width = np.where(traces["converged"] & np.isfinite(width), width, np.nan)
    finite = np.isfinite(width).any(axis=1)
    return float(np.median(np.nanmin(width[finite], axis=1))) if finite.any() else np.nan


def spacing_limit(traces: Traces) -> int:
    """Largest odd ROI (pixels) at which at most :data:`CROWDED_FRACTION` of the particles have
    a neighbour of their own stack inside it (the traces' ``crowded`` rule: a neighbour within
    ``roi // 2`` px on both axes); a very large number for a lone particle."""
    pos, stack = traces.position(), traces.stack
    gaps = np.full(len(pos), np.inf)
    for s in np.unique(stack):
        own = np.flatnonzero(stack == s)
        if own.size < 2:
            continue
        gap = np.abs(pos[own, None, :] - pos[None, own, :]).max(axis=2)
        np.fill_diagonal(gap, np.inf)
        gaps[own] = gap.min(axis=1)
    gap = float(np.quantile(gaps, CROWDED_FRACTION))
    if not np.isfinite(gap):
        return 1 << 20
    half = math.ceil(gap) - 1  # roi // 2 < gap
    return 2 * max(half, MIN_ROI // 2) + 1


def candidate_rois(width_px: float, upper: int) -> list[int]:
    """The odd ROI sizes to try (pixels): from :func:`roi_for_width` of the in-focus width
    ``width_px`` every :data:`ROI_STEP` px, :data:`N_CANDIDATES` at most, none above ``upper``
    (at least the first, capped at ``upper``)."""
    first = roi_for_width(width_px) if np.isfinite(width_px) and width_px > 0 else 15
    first = min(first, upper)
    return [r for r in range(first, first + ROI_STEP * N_CANDIDATES, ROI_STEP) if r <= upper]


def expected_errors(cal: Calibration) -> dict[str, np.ndarray]:
    """Expected z error (nm) of typical emitters on every plane of ``cal``'s stack (module
    notes, step 2): ``errors`` (n_kinds, n_z), one row per photon count of
    :data:`EMITTER_PHOTONS` and a last for emitters like the calibration particles, RMS over
    the kept particles; ``measured`` (n_z,) the fraction of them whose plane is usable;
    ``guess_nm`` the error of a guess; ``usable_nm`` the median over the kept particles of
    their usable range's ends (tilt-corrected z)."""
    local, shape, kept = cal.local, cal.shape, cal.kept
    use = np.zeros(cal.culled.size, bool)
    use[kept] = True
    use &= local.shapes[shape].inverse.valid
    cv = _cross_validated(local, shape, use, cal.positions, reference=uses_amplitude(shape))
    z = cal.traces.z_nm
    guess = float(np.ptp(z)) / np.sqrt(12.0)
    kinds = [
        np.hypot(dim_held_out(cal, photons),
                 crlb_sigma_z(local, cal.traces, shape, photons, roi_size=cal.roi_size,
                              readnoise=cal.camera.readnoise))  # fmt: skip
        for photons in EMITTER_PHOTONS
    ]
    kinds.append(np.abs(cv))
    errors = []
    for error in kinds:
        measured = np.isfinite(error)[kept]
        capped = np.where(measured, np.minimum(error[kept], guess), 0.0)
        count = measured.sum(axis=0)
        rms = np.sqrt(np.sum(capped**2, axis=0) / np.maximum(count, 1))
        errors.append(np.where(count > 0, rms, guess))  # none measured: a guess
    usable_nm = np.nanmedian(cal.usable_z_nm[kept], axis=0) if kept.size else [np.nan] * 2
    return {
        "errors": np.array(errors),
        "measured": np.isfinite(cv[kept]).mean(axis=0) if kept.size else np.zeros(z.size),
        "guess_nm": guess,
        "usable_nm": np.asarray(usable_nm, dtype=np.float64),
    }


def choose_roi(scores: dict[int, dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    """The ROI to calibrate with, from :func:`expected_errors` of each candidate that
    calibrated (module notes, step 3), and a JSON-able record of why: ``chosen``, a one-line
    ``reason`` and each candidate's ``core_nm``, ``range_nm``, ``usable_nm`` and ``kept``."""
    rois = sorted(scores)
    measured = np.array([scores[r]["measured"] for r in rois])
    core = np.all(measured >= 0.5, axis=0)
    if not core.any():  # no plane every candidate measures: judge on each one's own
        core = np.any(measured >= 0.5, axis=0)
    union = np.any(measured >= 0.5, axis=0)

    def rms(r: int, planes: np.ndarray) -> float:
        """RMS of candidate ``r``'s errors over ``planes``, a guess's where it measures fewer
        than half its particles."""
        if not planes.any():
            return np.inf
        own = scores[r]["measured"] >= 0.5
        errors = np.where(own, scores[r]["errors"], scores[r]["guess_nm"])
        return float(np.sqrt(np.mean(errors[:, planes] ** 2)))

    table = {
        r: {
            "core_nm": rms(r, core),
            "range_nm": rms(r, union),
            "usable_nm": [float(v) for v in scores[r]["usable_nm"]],
            "kept": int(scores[r].get("kept", 0)),
        }
        for r in rois
    }
    best_core = min(t["core_nm"] for t in table.values())
    eligible = [r for r in rois if table[r]["core_nm"] <= (1 + CORE_TOLERANCE) * best_core]
    eligible = eligible or rois  # no candidate measures anywhere: judged on range and size
    chosen = min(eligible, key=lambda r: (table[r]["range_nm"], r))
    row = table[chosen]
    lo, hi = row["usable_nm"]
    reason = (
        f"roi_size={chosen}: the best expected z error of 1e3-1e4-photon emitters and of "
        f"particles like the calibration's among ROIs {', '.join(map(str, rois))} px "
        f"({row['core_nm']:.0f} nm near focus, {row['range_nm']:.0f} nm over the stack; "
        f"usable z {lo:.0f} to {hi:.0f} nm)"
    )
    return chosen, {
        "chosen": chosen,
        "reason": reason,
        "candidates": {str(r): t for r, t in table.items()},
    }

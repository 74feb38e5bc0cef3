"""The ROI size from the data: the candidate whose calibration localizes typical emitters best.

A larger ROI holds more of a defocused spot, so it measures farther from focus; it also holds
more background, more of a neighbour's light and more of a defocused ring, whose fitted width
then depends on the ring's structure rather than on z, so near focus it can cost precision.
No rule on the spots' own fitted widths settles this (the width of a ring grows with the ROI it
is fitted in, and such a rule runs away). The ROI is therefore chosen by what it is for:

1. **Candidates** (:func:`candidate_rois`): the smallest odd ROI that holds 95 % of an
   in-focus spot (:func:`roi_for_width` of the particles' narrowest width), then every
   :data:`ROI_STEP` pixels, :data:`N_CANDIDATES` in all (so the ROI cannot run away from the
   in-focus spot), none larger than the images allow (:func:`roi_limit`) nor than the
   particles' spacing (:func:`spacing_limit`: at most a quarter of them with a neighbour
   inside their ROI).
2. **Score** (:func:`expected_errors`): each candidate is calibrated with each particle's own
   models, and on every plane of the stack the expected z error of typical emitters is taken
   over its kept particles: for emitters of 10³ and of 10⁴ photons, that of the particle's own
   image made into such an emitter over the images' background (:func:`frame_background`: a
   bright particle's fitted background holds its own halo in a small ROI, a dim emitter's
   does not), fitted as ``localize`` fits and localized by ``apply`` at the nearest other
   particle (:func:`~latentz.calibration.roi_emitters.emitter_errors`); for emitters like the
   calibration particles, the cross-validated error of the bright image (each particle's
   images localized with the nearest *other* particle's inverse model, as
   :mod:`~latentz.calibration.shape_choice` does). Inside a particle's usable range
   (:attr:`~latentz.calibration.Calibration.usable_planes`) an emitter not localized in range
   counts as a guess. Beyond it an emitter flagged out of range costs nothing (a shorter
   range), but one read in range is an *alias*: a defocused spot that looks like one inside
   the range (in a small ROI it is cut off where it outgrows the ROI, so its fitted widths
   stop growing), read at a wrong z with an error that does not say so. Any error above a
   guess anywhere in the stack (span/√12) counts as a guess.
3. **Choice** (:func:`choose_roi`): ``core_nm`` is the RMS of those errors over the *core*
   planes (where every candidate measures: at least half its kept particles usable, and some
   kind of emitter localized to better than half a guess; near focus), pooled with every alias
   of the stack; ``range_nm`` the same over every plane any candidate measures; each has a
   standard error over the particles (over the planes for a lone particle). Candidates cull
   different particles, and a candidate scored over the particles its culling kept would be
   judged on a selection, so each pair is compared over the particles both keep (the same
   stack, within :data:`SAME_PARTICLE_PX`): one *beats* the other when it errs less by more
   than their noise (the standard errors in quadrature) and more than :data:`CORE_TOLERANCE`.
   A candidate that keeps one particle is scored on that particle's own images read by its own
   models (nothing is held out), so it competes only where no candidate keeps two. The
   candidates that no other beats near focus are eligible (where each is beaten, those beaten
   by the fewest), and the smallest of them that no other of them beats over the range is
   chosen. So a larger ROI is taken only where it measures better beyond the noise and costs
   nothing near focus, and a shorter usable z range is preferred to lost precision near focus.
   A candidate whose calibration fails is skipped, so the choice never fails where a smaller
   ROI works.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import erfinv

from latentz.calibration.roi_emitters import emitter_errors
from latentz.calibration.shape import uses_amplitude
from latentz.calibration.shape_choice import _cross_validated

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration
    from latentz.calibration.traces import Traces
    from latentz.camera import Camera

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
    "frame_background",
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
N_CANDIDATES = 3
#: Most fraction of the particles allowed a neighbour inside their ROI (:func:`spacing_limit`).
CROWDED_FRACTION = 0.25
#: Photon counts of the typical single emitters the ROI is judged for.
EMITTER_PHOTONS = (1e3, 1e4)
#: One candidate beats another only where it errs less by more than this fraction and their
#: noise.
CORE_TOLERANCE = 0.05
#: Two candidates' kept particles are one particle where they lie in the same stack within
#: this many pixels on both axes.
SAME_PARTICLE_PX = 1.0


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


def frame_background(stacks: list[np.ndarray], camera: Camera) -> np.ndarray:
    """(n_stacks, n_z) background (photons per pixel) of each plane of each stack: the median
    pixel of the plane in photons, which sparse particles leave to the background."""
    return np.array([camera.to_photons(np.median(stack, axis=(1, 2))[:, None, None])[:, 0, 0]
                     for stack in stacks])  # fmt: skip


def expected_errors(
    cal: Calibration, stacks: list[np.ndarray], camera: Camera, background: np.ndarray
) -> dict[str, np.ndarray]:
    """Expected z error (nm) of typical emitters on every plane of ``cal``'s stack (module
    notes, step 2), from the calibration ``stacks`` (ADU) read by ``camera`` and their
    ``background`` ((n_stacks, n_z) photons per pixel, :func:`frame_background`):
    ``particles`` (n_kept, 3) each kept particle's stack and (x, y) position (pixels);
    ``particle_sq`` (n_kinds, n_kept, n_z) each kept particle's squared error capped at a
    guess's (NaN where its plane is not usable), one kind per photon count of
    :data:`EMITTER_PHOTONS` and a last for emitters like the calibration particles;
    ``alias_sq`` (n_kinds, n_kept, n_z) the same of the aliases (NaN where none);
    ``measured_each`` (n_kept, n_z) whether the particle's plane is usable and its bright image
    is read by its neighbour; ``guess_nm`` the error of a guess; ``usable_nm`` the median over
    the kept particles of their usable range's ends (tilt-corrected z)."""
    local, shape, kept = cal.local, cal.shape, cal.kept
    use = np.zeros(cal.culled.size, bool)
    use[kept] = True
    use &= local.shapes[shape].inverse.valid
    cv = _cross_validated(local, shape, use, cal.positions, reference=uses_amplitude(shape))
    z = cal.traces.z_nm
    guess = float(np.ptp(z)) / np.sqrt(12.0)
    usable = cal.usable_planes  # beyond it a read in range is an alias
    errors = np.abs([emitter_errors(cal, stacks, camera, background, photons)
                     for photons in EMITTER_PHOTONS] + [cv])[:, kept]  # fmt: skip
    capped = np.minimum(errors, guess) ** 2  # inf: not localized, a guess; NaN stays
    usable = usable[kept]
    usable_nm = np.nanmedian(cal.usable_z_nm[kept], axis=0) if kept.size else [np.nan] * 2
    return {
        "particles": np.column_stack([cal.traces.stack[kept], cal.positions[kept]]),
        "particle_sq": np.where(usable, capped, np.nan),
        "alias_sq": np.where(usable | ~np.isfinite(errors), np.nan, capped),  # inf: out of range
        "measured_each": usable & ~np.isnan(cv[kept]),
        "guess_nm": guess,
        "usable_nm": np.asarray(usable_nm, dtype=np.float64),
    }


def choose_roi(scores: dict[int, dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    """The ROI to calibrate with, from :func:`expected_errors` of each candidate that
    calibrated (module notes, step 3), and a JSON-able record of why: ``chosen``, a one-line
    ``reason`` and each candidate's ``core_nm`` and ``range_nm`` over its own kept particles
    with their standard errors (``core_se_nm``, ``range_se_nm``), ``usable_nm``, ``kept`` and
    ``beaten_by`` (near focus and over the range, the candidates that beat it over the
    particles both keep)."""
    rois = sorted(scores)
    held_out = [r for r in rois if len(scores[r]["particles"]) >= 2] or rois
    own = {r: _judged(scores[r], np.ones(len(scores[r]["particles"]), bool)) for r in rois}
    measured = np.array([_measures(own[r]) for r in held_out])
    core = np.all(measured, axis=0)
    if not core.any():  # no plane every candidate measures: judge on each one's own
        core = np.any(measured, axis=0)
    planes = {"core": core, "range": np.any(measured, axis=0)}
    table = {}
    for r in rois:
        table[r] = {"usable_nm": [float(v) for v in scores[r]["usable_nm"]],
                    "kept": len(scores[r]["particles"])}  # fmt: skip
        for name, where in planes.items():
            value, se = _rms_over(own[r], where)
            table[r] |= {f"{name}_nm": value, f"{name}_se_nm": se}

    def beaten(rivals: list[int], name: str) -> dict[int, list[int]]:
        return {r: [o for o in rivals if o != r and _beats(scores[o], scores[r], planes[name])]
                for r in rivals}  # fmt: skip

    near = beaten(held_out, "core")
    eligible = _least_beaten(near)
    far = beaten(eligible, "range")
    chosen = min(_least_beaten(far))
    for r in rois:
        table[r]["beaten_by"] = {"core": near.get(r, []), "range": far.get(r, [])}
    row = table[chosen]
    lo, hi = row["usable_nm"]
    reason = (
        f"roi_size={chosen}: the smallest with the best expected z error of 1e3-1e4-photon "
        f"emitters and of particles like the calibration's among ROIs "
        f"{', '.join(map(str, rois))} px, each pair compared over the particles both keep "
        f"({row['core_nm']:.0f} nm near focus, {row['range_nm']:.0f} nm over the stack; usable "
        f"z {lo:.0f} to {hi:.0f} nm)"
    )
    return chosen, {
        "chosen": chosen,
        "reason": reason,
        "candidates": {str(r): t for r, t in table.items()},
    }


def _least_beaten(beaten_by: dict[int, list[int]]) -> list[int]:
    """The candidates that no other beats, or where each is beaten (scored over different
    particles, A can beat B, B beat C and C beat A), those beaten by the fewest."""
    fewest = min(len(rivals) for rivals in beaten_by.values())
    return [r for r, rivals in beaten_by.items() if len(rivals) == fewest]


def _beats(one: dict[str, Any], other: dict[str, Any], planes: np.ndarray) -> bool:
    """Whether candidate ``one`` errs less than ``other`` over ``planes`` (:func:`_rms_over`)
    by more than their noise (the two standard errors in quadrature) and more than
    :data:`CORE_TOLERANCE`, both scored over the particles both keep (:func:`_shared`; over
    their own where fewer than two are shared)."""
    rows = _shared(one["particles"], other["particles"])
    if min(rows[0].sum(), rows[1].sum()) < 2:
        rows = (np.ones(len(one["particles"]), bool), np.ones(len(other["particles"]), bool))
    a, se_a = _rms_over(_judged(one, rows[0]), planes)
    b, se_b = _rms_over(_judged(other, rows[1]), planes)
    return bool(b - a > max(CORE_TOLERANCE * a, math.hypot(se_a, se_b)))


def _shared(one: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of the particles ``one`` (n, 3) and ``other`` (m, 3) (stack, x, y pixels) the other
    keeps too: one in the same stack within :data:`SAME_PARTICLE_PX` on both axes."""
    same = (np.abs(one[:, None, 1:] - other[None, :, 1:]).max(axis=2) <= SAME_PARTICLE_PX) & (
        one[:, None, 0] == other[None, :, 0]
    )
    return same.any(axis=1), same.any(axis=0)


def _judged(score: dict[str, Any], rows: np.ndarray) -> dict[str, Any]:
    """A candidate's score over its kept particles ``rows`` (bool): ``errors`` (n_kinds, n_z),
    the RMS over them of each plane's measured errors (a guess's where none is); ``measured``,
    the fraction of them measured on each plane; their ``particle_sq`` and ``alias_sq``."""
    squares = score["particle_sq"][:, rows]
    count = np.isfinite(squares).sum(axis=1)
    rms = np.sqrt(np.nansum(squares, axis=1) / np.maximum(count, 1))
    measured = score["measured_each"][rows]
    return {
        "errors": np.where(count > 0, rms, score["guess_nm"]),
        "particle_sq": squares,
        "alias_sq": score["alias_sq"][:, rows],
        "measured": measured.mean(axis=0) if rows.any() else np.zeros(measured.shape[1]),
        "guess_nm": score["guess_nm"],
    }


def _measures(score: dict[str, Any]) -> np.ndarray:
    """(n_z,) the planes where a candidate measures: at least half its kept particles usable,
    and some kind of emitter localized to better than half a guess."""
    best = np.min(score["errors"], axis=0)
    return (score["measured"] >= 0.5) & (best < score["guess_nm"] / 2)


def _rms_over(score: dict[str, Any], planes: np.ndarray) -> tuple[float, float]:
    """RMS (nm) of one candidate's errors over ``planes`` (a guess's where it measures fewer
    than half its particles) pooled with its aliases (``alias_sq``: emitters from planes beyond
    a particle's usable range that are read in range, anywhere in the stack), and its standard
    error over the particles (delta method on each particle's mean square; over the planes for
    a lone particle)."""
    if not planes.any():
        return np.inf, 0.0
    own = score["measured"] >= 0.5
    errors = np.where(own, score["errors"], score["guess_nm"])[:, planes]
    alias = score["alias_sq"]
    n_kept = max(alias.shape[1], 1)
    weight = errors.size * n_kept  # each kind and plane holds every kept particle
    value = float(np.sqrt((np.sum(errors**2) * n_kept + np.nansum(alias))
                          / (weight + np.isfinite(alias).sum())))  # fmt: skip
    squares = np.where(own, score["particle_sq"], score["guess_nm"] ** 2)[:, :, planes]
    per = np.moveaxis(squares, 1, 0).reshape(squares.shape[1], -1)  # (n_kept, entries)
    aliased = np.moveaxis(alias, 1, 0).reshape(per.shape[0], -1)
    per = np.concatenate([per, aliased[:, np.isfinite(aliased).any(axis=0)]], axis=1)
    samples = np.nanmean(per, axis=1)
    if np.isfinite(samples).sum() < 2:  # a lone particle: its planes' noise draws instead
        samples = np.nanmean(squares, axis=(0, 1))
    samples = samples[np.isfinite(samples)]
    if samples.size < 2:
        return value, 0.0
    se_square = float(np.std(samples, ddof=1) / np.sqrt(samples.size))
    return value, se_square / (2 * value) if value > 0 else 0.0

"""The automatic ROI of `calibrate(roi_size=None)`: its candidates, the bound the particles'
spacing sets, and the choice between candidates (:mod:`latentz.calibration.roi`)."""

import warnings

import numpy as np
import pytest

from latentz.calibration.roi import (
    CORE_TOLERANCE,
    CROWDED_FRACTION,
    MIN_ROI,
    N_CANDIDATES,
    ROI_STEP,
    candidate_rois,
    choose_roi,
    focus_width_px,
    roi_for_width,
    spacing_limit,
)
from latentz.calibration.traces import Traces


def _traces(points: np.ndarray, stack: np.ndarray | None = None, widths=None) -> Traces:
    n, n_z = len(points), 5
    widths = np.full((n, n_z), 1.5) if widths is None else widths
    data = {k: np.ones((n, n_z)) for k in ("amplitude", "background", "rho")}
    data.update(x=np.repeat(points[:, :1], n_z, 1), y=np.repeat(points[:, 1:], n_z, 1),
                wx=widths, wy=widths, rho=np.zeros((n, n_z)))  # fmt: skip
    return Traces(np.arange(n_z) * 100.0, data, stack=stack)


def _crowded_fraction(points: np.ndarray, roi: int) -> float:
    """The traces' own crowded rule: a neighbour within roi // 2 px on both axes."""
    gap = np.abs(points[:, None] - points[None]).max(axis=2)
    np.fill_diagonal(gap, np.inf)
    return float(np.mean(gap.min(axis=1) <= roi // 2))


@pytest.mark.parametrize("seed", range(4))
def test_spacing_limit_is_the_largest_roi_that_crowds_at_most_a_quarter(seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 200, (40, 2))
    roi = spacing_limit(_traces(points))
    assert roi % 2 == 1
    assert _crowded_fraction(points, roi) <= CROWDED_FRACTION
    assert _crowded_fraction(points, roi + 2) > CROWDED_FRACTION


def test_spacing_counts_neighbours_of_the_same_stack_only():
    a = np.array([[10.0, 10.0], [40.0, 10.0], [10.0, 40.0], [40.0, 40.0]])
    points = np.vstack([a, a + 3.0])  # the second stack is another field of view
    stack = np.repeat([0, 1], 4)
    assert spacing_limit(_traces(points, stack)) == spacing_limit(_traces(a))
    assert spacing_limit(_traces(a)) == 2 * (30 - 1) + 1  # roi // 2 < 30 px


def test_candidates_start_at_the_in_focus_spot_and_stop_at_the_bound():
    width = 1.8
    first = roi_for_width(width)
    assert candidate_rois(width, 1000) == [first + ROI_STEP * k for k in range(N_CANDIDATES)]
    assert candidate_rois(width, first + ROI_STEP) == [first, first + ROI_STEP]
    assert candidate_rois(width, MIN_ROI) == [MIN_ROI]  # the bound wins over the spot


def test_focus_width_is_the_narrowest_geometric_mean_width():
    widths = np.array([[3.0, 2.0, 1.2, 2.0, 3.0]] * 3)
    traces = _traces(np.array([[0.0, 0.0], [50.0, 0.0], [0.0, 50.0]]), widths=widths)
    assert focus_width_px(traces) == pytest.approx(1.2)


def _particles(n: int, stack: int = 0) -> np.ndarray:
    """(n, 3) stack and (x, y) positions (pixels) of ``n`` particles 40 px apart on a row."""
    return np.column_stack([np.full(n, stack), 40.0 * np.arange(n), np.full(n, 20.0)])


def _score(core: float, far: float, measured_far: bool = True, kept: int = 10) -> dict:
    """One candidate's expected errors on 6 planes, 4 near focus and 2 far, alike for each of
    the ``kept`` particles of :func:`_particles` and each kind of emitter."""
    measured = np.array([True] * 4 + [measured_far] * 2)
    squares = np.where(measured, np.array([core] * 4 + [far] * 2) ** 2, np.nan)
    return {"particles": _particles(kept),
            "particle_sq": np.tile(squares, (3, kept, 1)),
            "alias_sq": np.full((3, kept, 6), np.nan),
            "measured_each": np.tile(measured, (kept, 1)),
            "guess_nm": 1000.0, "usable_nm": np.array([-1.0, 1.0])}  # fmt: skip


def test_a_roi_that_costs_precision_near_focus_loses_to_a_shorter_range():
    scores = {15: _score(30.0, 0.0, measured_far=False),
              21: _score(30.0 * (1 + 2 * CORE_TOLERANCE), 40.0)}  # fmt: skip
    chosen, record = choose_roi(scores)
    assert chosen == 15 and record["chosen"] == 15
    assert "roi_size=15" in record["reason"] and set(record["candidates"]) == {"15", "21"}


def test_a_roi_as_good_near_focus_wins_by_its_range():
    scores = {15: _score(30.0, 0.0, measured_far=False),
              21: _score(30.0 * (1 + CORE_TOLERANCE / 2), 40.0)}  # fmt: skip
    assert choose_roi(scores)[0] == 21


def test_a_roi_that_keeps_one_particle_loses_to_one_whose_errors_are_held_out():
    """A lone particle's emitters are read by its own models: its better score is in-sample."""
    lone = _score(20.0, 30.0, kept=1)
    assert choose_roi({11: _score(30.0, 60.0), 15: lone})[0] == 11
    # where every candidate keeps one particle, the rule judges them as it judges any
    assert choose_roi({11: _score(30.0, 60.0, kept=1), 15: lone})[0] == 15


def test_rois_are_compared_over_the_particles_both_keep():
    """A 9 px ROI keeps 32 of the 103 particles a 13 px one keeps, and its culling selected
    the particles whose errors are small: over its own it errs 25 nm near focus, the 13 px ROI
    30 nm over all of its own. Over the 32 they share the 13 px ROI errs 20 nm, and wins; where
    it errs 10 % more than the 9 px ROI over them, the 9 px ROI wins though it keeps fewer."""
    culled = _score(25.0, 0.0, measured_far=False, kept=32)
    kept = _score(30.0, 40.0, kept=103)
    for shared_nm, chosen in ((20.0, 13), (25.0 * (1 + 2 * CORE_TOLERANCE), 9)):
        kept["particle_sq"][:, :32, :4] = shared_nm**2
        choice, record = choose_roi({9: culled, 13: kept})
        assert choice == chosen
        assert record["candidates"][str(22 - chosen)]["beaten_by"]["core"] == [chosen]
        assert [record["candidates"][r]["kept"] for r in ("9", "13")] == [32, 103]


def test_particles_are_shared_only_within_a_pixel_in_the_same_stack():
    """Two ROIs keep 10 particles each; the 15 px one errs 60 nm on the last 5, 30 nm like the
    11 px one on the rest, and loses where they are the same particles (within a pixel, in the
    same stack). Where its last 5 lie in another stack or 2 px away, the two are compared over
    the first 5 only, and tie: the smaller wins, and neither is beaten."""
    small, large = _score(30.0, 40.0), _score(30.0, 40.0)
    large["particle_sq"][:, 5:] = 60.0**2
    large["particles"][:5, 1] += 0.8
    assert choose_roi({11: small, 15: large})[1]["candidates"]["15"]["beaten_by"]["core"] == [11]
    for moved in (_particles(10, stack=1), _particles(10) + [0.0, 2.0, 0.0]):
        large["particles"] = np.concatenate([_particles(5), moved[5:]])
        chosen, record = choose_roi({11: small, 15: large})
        assert chosen == 11 and record["candidates"]["15"]["beaten_by"]["core"] == []
        assert choose_roi({15: small, 11: large})[0] == 11  # the tie goes to the smaller


def test_where_each_roi_is_beaten_those_beaten_least_are_eligible():
    """Scored over different particles, 13 px beats 17 px, 17 px beats 21 px and 21 px beats
    13 px near focus (20 against 30 nm over the two particles each pair shares), and all three
    beat 11 px, which errs 40 nm on every particle. No ROI is unbeaten; 11 px, beaten most,
    must not win by its size."""
    errors_nm = {13: [30, 30, 20, 20, 0, 0], 17: [0, 0, 30, 30, 20, 20],
                 21: [20, 20, 0, 0, 30, 30], 11: [40] * 6}  # fmt: skip
    scores = {}
    for r, errors in errors_nm.items():
        rows = np.flatnonzero(errors)
        scores[r] = _score(40.0, 40.0, kept=rows.size)
        scores[r]["particles"] = _particles(6)[rows]
        scores[r]["particle_sq"][:, :, :4] = np.asarray(errors, float)[rows, None] ** 2
    chosen, record = choose_roi(scores)
    assert chosen == 13
    assert [record["candidates"][str(r)]["beaten_by"]["core"] for r in (11, 13, 17, 21)] == [
        [13, 17, 21], [21], [13], [17]]  # fmt: skip


def test_a_roi_that_reads_emitters_beyond_its_range_in_range_loses():
    """Beyond the usable range a spot that has outgrown a small ROI can look like one inside
    it: read in range, its z is wrong by microns and its reported error does not say so. Two
    ROIs equal near focus and over the range: the one whose emitters from beyond its particles'
    usable range are read in range (a tenth of them, 1.5 µm off) loses to the one that flags
    them out of range, though it is smaller."""
    honest, aliasing = _score(30.0, 40.0), _score(30.0, 40.0)
    aliasing["alias_sq"][:2, :1, :] = 1500.0**2  # the dim kinds
    chosen, record = choose_roi({11: aliasing, 15: honest})
    assert chosen == 15
    assert record["candidates"]["11"]["core_nm"] > 2 * record["candidates"]["15"]["core_nm"]
    # without the aliases the smaller one wins the tie
    aliasing["alias_sq"][:] = np.nan
    assert choose_roi({11: aliasing, 15: honest})[0] == 11


def test_the_smaller_roi_wins_a_tie():
    assert choose_roi({19: _score(30.0, 40.0), 15: _score(30.0, 40.0)})[0] == 15


def test_frame_background_is_the_sparse_stacks_background():
    from latentz.calibration.roi import frame_background
    from latentz.camera import Camera

    rng = np.random.default_rng(0)
    camera = Camera(offset=100.0, gain=0.5, readnoise=1.5)
    levels = np.array([5.0, 20.0, 80.0])  # photons per pixel, one per plane
    yy, xx = np.mgrid[:96, :96]
    spots = sum(2000 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 2.0**2))
                for cx, cy in rng.uniform(10, 86, (6, 2)))  # fmt: skip
    photons = rng.poisson(levels[:, None, None] + spots[None])
    got = frame_background([camera.to_adu(photons)], camera)[0]
    # the median of integer Poisson counts lies within 1 photon of the mean; the spots hold
    # ~5 % of the pixels and move it by well under that
    np.testing.assert_allclose(got, levels, atol=1.0)


def test_emitters_from_the_particles_images_err_at_least_as_much_as_their_bound():
    """On latentz's simulator (12 particles, ±1 µm), an emitter made from a particle's image is
    localized no better than the Cramér–Rao bound of such an emitter near focus (within three
    standard errors of an RMS from n samples, 1/sqrt(2n)), and no worse than twice that bound in
    quadrature with the bright images' own held-out error; dimmer emitters err more."""
    from dataclasses import replace

    from latentz import simulate as sim
    from latentz.calibration import calibrate
    from latentz.calibration.precision import crlb_sigma_z
    from latentz.calibration.roi import frame_background
    from latentz.calibration.roi_emitters import emitter_errors
    from latentz.calibration.shape_choice import _cross_validated

    data = sim.calibration_dataset(n_particles=12, z_nm=np.linspace(-1000, 1000, 21), seed=3,
                                   n_stage_positions=1, frame_shape=(160, 160),
                                   min_spacing_px=30.0)  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(list(data.stacks), data.z_nm, camera=data.camera, roi_size=13,
                        field_model="nearest")  # fmt: skip
    background = frame_background(data.stacks, data.camera)
    traces = replace(cal.traces, data={**cal.traces.data,
                                       "background": background[cal.traces.stack]})  # fmt: skip
    kept, near = cal.kept, slice(6, 15)  # the planes within ±400 nm
    use = np.zeros(len(cal.traces), bool)
    use[kept] = True
    bright = _cross_validated(cal.local, cal.shape, use, cal.positions)[kept][:, near]
    rms = {}
    for photons in (1e3, 1e4, 1e5):
        err = emitter_errors(cal, data.stacks, data.camera, background, photons)[kept][:, near]
        rms[photons] = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2)))
        if photons == 1e3:
            continue
        bound = crlb_sigma_z(cal.local, traces, cal.shape, photons, roi_size=13,
                             readnoise=data.camera.readnoise)[kept][:, near]  # fmt: skip
        n = int(np.isfinite(err).sum())
        crlb = float(np.sqrt(np.nanmean(bound**2)))
        assert n >= 0.7 * err.size
        assert rms[photons] >= crlb * (1 - 3 / np.sqrt(2 * n))
        assert rms[photons] <= 2 * np.hypot(crlb, np.sqrt(np.nanmean(bright**2)))
    assert rms[1e3] > rms[1e4] > rms[1e5]

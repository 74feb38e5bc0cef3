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


def _score(core: float, far: float, measured_far: bool = True) -> dict:
    """One candidate's expected errors on 6 planes: 4 near focus, 2 far."""
    errors = np.array([[core] * 4 + [far] * 2] * 3)
    measured = np.array([1.0] * 4 + [1.0 if measured_far else 0.0] * 2)
    return {"errors": errors, "measured": measured, "guess_nm": 1000.0,
            "usable_nm": np.array([-1.0, 1.0]), "kept": 10}  # fmt: skip


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
    lone = _score(20.0, 30.0) | {"kept": 1}
    assert choose_roi({11: _score(30.0, 60.0), 15: lone})[0] == 11
    # where every candidate keeps one particle, the rule judges them as it judges any
    assert choose_roi({11: _score(30.0, 60.0) | {"kept": 1}, 15: lone})[0] == 15


def test_a_roi_that_culls_most_particles_loses_to_one_that_keeps_them():
    """A small ROI that keeps 32 of the 103 particles a larger one keeps is scored over the
    particles its culling selected (family draw 18: 652 against 723 nm near focus); the larger
    ROI is chosen unless every candidate keeps as few."""
    culled = _score(25.0, 0.0, measured_far=False) | {"kept": 32}
    assert choose_roi({9: culled, 13: _score(30.0, 40.0) | {"kept": 103}})[0] == 13
    assert choose_roi({9: culled, 13: _score(30.0, 40.0) | {"kept": 60}})[0] == 9


def test_a_roi_that_reads_emitters_beyond_its_range_in_range_loses():
    """Beyond the usable range a spot that has outgrown a small ROI can look like one inside
    it: read in range, its z is wrong by microns and its reported error does not say so. Two
    ROIs equal near focus and over the range: the one whose emitters from beyond its particles'
    usable range are read in range (a tenth of them, 1.5 µm off) loses to the one that flags
    them out of range, though it is smaller."""
    honest, aliasing = _score(30.0, 40.0), _score(30.0, 40.0)
    n_kinds, n_z = honest["errors"].shape
    for score in (honest, aliasing):
        score["particle_sq"] = np.full((n_kinds, score["kept"], n_z), 30.0**2)
        score["alias_sq"] = np.full((n_kinds, score["kept"], n_z), np.nan)
    aliasing["alias_sq"][:2, : aliasing["kept"] // 10, :] = 1500.0**2  # the dim kinds
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

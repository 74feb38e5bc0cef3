"""The automatic ROI of `calibrate(roi_size=None)`: its candidates, the bound the particles'
spacing sets, and the choice between candidates (:mod:`latentz.calibration.roi`)."""

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


def test_the_smaller_roi_wins_a_tie():
    assert choose_roi({19: _score(30.0, 40.0), 15: _score(30.0, 40.0)})[0] == 15

"""The SMLM 2016 challenge's scoring against cases worked out by hand."""

import numpy as np
import pandas as pd
import pytest

from latentz.validation.challenge import challenge_score, efficiency, match_frame


def _table(rows):
    return pd.DataFrame(rows, columns=["frame", "x_nm", "y_nm", "z_nm"])


@pytest.mark.parametrize(
    ("jaccard", "rmse", "alpha", "expected"),
    [
        (100.0, 0.0, 1.0, 100.0),  # perfect
        (70.0, 40.0, 1.0, 50.0),  # sqrt(30² + 40²) = 50
        (70.0, 80.0, 0.5, 50.0),  # sqrt(30² + (0.5·80)²) = 50
        (0.0, 0.0, 1.0, 0.0),  # nothing found
        (100.0, 300.0, 1.0, -200.0),  # no lower bound
    ],
)
def test_efficiency_formula(jaccard, rmse, alpha, expected):
    assert efficiency(jaccard, rmse, alpha) == pytest.approx(expected)


def test_matching_keeps_the_most_pairs_not_the_nearest_first():
    # truths at x = 0 and 200; loc 90 is nearest to 0, but loc -140 can only pair with 0
    # (340 nm from 200): nearest-first pairing gives 1 pair, the assignment gives 2.
    truth = np.array([[0.0, 0, 0], [200.0, 0, 0]])
    locs = np.array([[90.0, 0, 0], [-140.0, 0, 0]])
    ti, li = match_frame(truth, locs)
    assert sorted(zip(ti.tolist(), li.tolist(), strict=True)) == [(0, 1), (1, 0)]


def test_matching_takes_the_smaller_total_distance_among_equal_counts():
    truth = np.array([[0.0, 0, 0], [100.0, 0, 0]])
    locs = np.array([[10.0, 0, 0], [95.0, 0, 0]])  # 10 + 5 against 95 + 90
    ti, li = match_frame(truth, locs)
    assert dict(zip(ti.tolist(), li.tolist(), strict=True)) == {0: 0, 1: 1}


@pytest.mark.parametrize(
    ("loc", "matched"),
    [
        ((150.0, 200.0, 0.0), True),  # 250 nm laterally: on the limit
        ((150.0, 200.1, 0.0), False),
        ((0.0, 0.0, 500.0), True),  # 500 nm axially: on the limit
        ((0.0, 0.0, -500.1), False),
        ((3.0, 4.0, 499.0), True),
    ],
)
def test_matching_tolerances_are_lateral_and_axial(loc, matched):
    ti, _ = match_frame(np.zeros((1, 3)), np.array([loc]))
    assert len(ti) == int(matched)


def test_score_of_a_hand_worked_case():
    truth = _table([(0, 0, 0, 0), (0, 1000, 0, 0), (1, 0, 0, 0), (2, 0, 0, 0)])
    locs = _table(
        [
            (0, 30, 40, 0),  # TP: 50 nm laterally
            (0, 1000, 0, 100),  # TP: 100 nm axially
            (0, 5000, 0, 0),  # FP: nothing within 250 nm
            (2, 0, 0, np.nan),  # no z: not a localization, so frame 2's emitter is a FN
            (2, 400, 0, 0),  # FP: 400 nm away
        ]
    )  # frame 1's emitter: FN
    s = challenge_score(truth, locs)
    assert (s["tp"], s["fp"], s["fn"], s["n_locs"]) == (2, 2, 2, 4)
    assert s["jaccard_pct"] == pytest.approx(100 * 2 / 6)
    assert s["rmse_lateral_nm"] == pytest.approx(np.sqrt(50**2 / 2))
    assert s["rmse_axial_nm"] == pytest.approx(np.sqrt(100**2 / 2))
    j = 100 * 2 / 6
    assert s["e_lateral"] == pytest.approx(100 - np.hypot(100 - j, np.sqrt(1250)))
    assert s["e_axial"] == pytest.approx(100 - np.hypot(100 - j, 0.5 * np.sqrt(5000)))
    assert s["e_3d"] == pytest.approx((s["e_lateral"] + s["e_axial"]) / 2)
    assert s["bias_z_nm"] == pytest.approx(50.0)


def test_pairs_are_made_within_frames_only():
    truth = _table([(0, 0, 0, 0)])
    s = challenge_score(truth, _table([(1, 0, 0, 0)]))  # same place, other frame
    assert (s["tp"], s["fp"], s["fn"]) == (0, 1, 1)
    assert np.isnan(s["rmse_lateral_nm"])


def test_missing_columns_are_named():
    with pytest.raises(ValueError, match=r"locs.*missing: \['z_nm'\]"):
        challenge_score(_table([(0, 0, 0, 0)]), _table([]).drop(columns="z_nm"))


def test_a_fit_within_the_error_of_a_more_precise_one_is_one_measurement():
    from latentz.validation.molecules import one_per_measurement

    # frame 0: a fit, its copy 0.01 px off (within the better one's 0.05 px), a fit 0.5 px away
    # (beyond it), a fit without a position; frame 1: the copy's place, another frame's fit
    locs = pd.DataFrame(
        {
            "frame": [0, 0, 0, 0, 1],
            "x": [10.0, 10.01, 10.5, np.nan, 10.01],
            "y": [5.0, 5.0, 5.0, np.nan, 5.0],
            "x_err": [0.04, 0.05, 0.04, np.nan, 0.04],
            "y_err": [0.03, 0.03, 0.03, np.nan, 0.03],
        }
    )
    np.testing.assert_array_equal(one_per_measurement(locs), [True, False, True, True, True])
    # the more precise of two copies is the one kept, whichever comes first
    swapped = locs.assign(x_err=[0.06, 0.04, 0.04, np.nan, 0.04])
    np.testing.assert_array_equal(one_per_measurement(swapped), [False, True, True, True, True])

"""Linking keeps particle identities through missed detections."""

import numpy as np
import pytest

from latentz.motion.linking import link
from latentz.motion.rigid import rigid_motion
from latentz.simulate.gear_motion import gear_trajectory


def _detections(truth, *, missing, seed):
    """Noisy (2 nm lateral, 80 nm axial) detections with a fraction `missing` dropped at random,
    shuffled, true identity kept in `truth` for checking only."""
    rng = np.random.default_rng(seed)
    locs = truth.positions.copy()
    locs[["x_nm", "y_nm"]] += rng.normal(0.0, 2.0, (len(locs), 2))
    locs["z_nm"] += rng.normal(0.0, 80.0, len(locs))
    locs = locs[rng.random(len(locs)) >= missing]
    return locs.rename(columns={"particle": "truth"}).sample(frac=1.0, random_state=seed)


def _assert_identities_kept(linked, n_particles):
    assert linked.groupby("particle")["truth"].nunique().max() == 1  # no swaps
    assert linked.groupby("truth")["particle"].nunique().max() == 1  # no broken tracks
    assert linked["particle"].nunique() == n_particles


def test_predictive_linking_follows_98_mrad_steps_with_5_percent_missing():
    # Rim particles move ~15 µm per cycle, more than the 5 µm minimum spacing. The prediction
    # error is the rotational play: std sqrt(2) * 5 mrad at r <= 156 µm is <= 1.1 µm, so a 5 µm
    # search range is > 4 sigma; memory 3 bridges runs of misses (0.05**4 per particle-frame).
    truth = gear_trajectory(150, seed=3)
    locs = _detections(truth, missing=0.05, seed=1)
    linked = link(locs, search_range_nm=5000.0, memory=3, predict=True)
    assert len(linked) == len(locs) and linked["frame"].is_monotonic_increasing
    _assert_identities_kept(linked, 28)
    relinked = rigid_motion(linked.drop(columns="truth"))
    direct = rigid_motion(locs.rename(columns={"truth": "particle"}))
    np.testing.assert_allclose(relinked["gamma"], direct["gamma"], rtol=1e-12)


def test_plain_linking_of_small_steps_with_5_percent_missing():
    # 2000 steps per revolution: 3 mrad, < 0.5 µm per cycle; the 400 nm clearance adds < 0.4 µm.
    truth = gear_trajectory(100, steps_per_rev=2000, rotation_play_mrad=0.5, seed=4)
    locs = _detections(truth, missing=0.05, seed=2)
    linked = link(locs, search_range_nm=2000.0, memory=3)
    _assert_identities_kept(linked, 28)


def test_without_prediction_large_steps_break_identities():
    truth = gear_trajectory(30, seed=3)
    linked = link(_detections(truth, missing=0.0, seed=5), search_range_nm=5000.0)
    assert linked["particle"].nunique() > 28


@pytest.mark.parametrize(
    ("change", "kwargs", "error", "match"),
    [
        (lambda t: t.drop(columns="y_nm"), {}, ValueError, "y_nm"),
        (lambda t: t, {"search_range_nm": -1.0}, ValueError, "search_range_nm"),
        (lambda t: t, {"memory": -1}, ValueError, "memory"),
        (lambda t: t, {"memory": 1.5}, TypeError, "memory"),
        (lambda t: t.iloc[:0], {}, ValueError, "at least one"),
        (lambda t: t.assign(z_nm=np.inf), {}, ValueError, "non-finite"),
        (lambda t: t, {"predict": True, "first_cycle_range_nm": 0.0}, ValueError, "first_cycle"),
    ],
)
def test_bad_input_is_refused(change, kwargs, error, match):
    locs = gear_trajectory(3, n_particles=5).positions.drop(columns="particle")
    options = {"search_range_nm": 1000.0, **kwargs}
    with pytest.raises(error, match=match):
        link(change(locs), **options)

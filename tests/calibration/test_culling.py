"""Culling: defective particles (dimers, oversized) against a population of good ones."""

import numpy as np
import pandas as pd
from calib_synthetic import make_traces

from latentz.calibration.culling import cull, neighbour_offsets, robust_z
from latentz.calibration.workflow import calibrate_traces
from latentz.camera import Camera


def test_dimers_and_large_particles_are_culled_and_good_ones_kept():
    rng = np.random.default_rng(13)
    n = 400
    defect = np.full(n, "none", dtype=object)
    bad = rng.choice(n, 12, replace=False)  # 3 %
    defect[bad[:6]] = "dimer"
    defect[bad[6:]] = "large"
    traces, truth = make_traces(n, defect=defect, seed=13)
    cal = calibrate_traces(traces, camera=Camera(), field_model="nearest")
    culled = cal.particles["culled"].to_numpy()
    is_bad = defect != "none"
    assert culled[is_bad].mean() >= 0.9
    assert culled[~is_bad].mean() <= 0.02
    # every culled particle says why
    assert (cal.particles.loc[culled, "cull_reason"] != "").all()
    assert (cal.particles.loc[~culled, "cull_reason"] == "").all()


def test_robust_statistics_ignore_the_outliers():
    rng = np.random.default_rng(14)
    values = rng.normal(10.0, 2.0, 1000)
    values[:20] = 1e6
    z = robust_z(values, np.ones(1000, bool))
    # median/MAD of the 980 good values: the scale is 2 within the MAD's 2.5 % sampling error
    assert abs(np.std(z[20:]) - 1) < 0.1
    assert np.all(z[:20] > 1e4)


def test_neighbour_offsets_remove_a_smooth_field_trend():
    rng = np.random.default_rng(15)
    pos = rng.uniform(0, 100, (500, 2))
    values = 0.5 * pos[:, 0] + rng.normal(0, 0.1, 500)  # trend of 50 across the field
    values[7] += 5.0
    off = neighbour_offsets(values, pos, np.ones(500, bool), k=8)
    # the 8 neighbours lie within r ~ 7 units, their median x within ~1.25 (r/2)/sqrt(8) ~ 1.5
    # of the particle's: the trend leaves an SD of ~0.8, a twentieth of the raw SD (14)
    assert np.std(np.delete(off, 7)) < 0.1 * np.std(values)
    assert off[7] > 3.0


def test_hard_failures_carry_their_reason():
    features = pd.DataFrame({"log_photons": np.zeros(4)})
    hard = {"never_in_focus": np.array([False, True, False, False])}
    culled, reason, _ = cull(features, hard)
    assert culled.tolist() == [False, True, False, False]
    assert reason[1] == "never_in_focus"

"""Issue 6, Show 6: images -> localize -> calibrate/apply -> link -> rigid motion, against the
simulated gear's true motion, within the Monte Carlo uncertainty."""

import numpy as np

from latentz.calibration import calibrate
from latentz.localization import localize
from latentz.pipeline import track_tables


def test_gamma_per_cycle_agrees_with_truth_within_uncertainty(small_microscope):
    data, gear = small_microscope.calibration, small_microscope.gear
    cal = calibrate(list(data.stacks), data.z_nm, camera=data.camera, field_model="nearest")
    spots = localize(gear.frames, camera=gear.camera, roi_size=15)
    locs = cal.apply(spots[spots["converged"]])
    assert locs["in_range"].mean() > 0.9
    tables = track_tables(locs, n_sim=2000, seed=1)
    motion, sigma = tables["motion"], tables["uncertainty"]
    truth = gear.gear.motion_about(np.asarray(motion.attrs["centre_nm"]))
    both = motion.merge(truth, on="frame", suffixes=("", "_true"))
    assert len(both) == gear.frames.shape[0] - 1
    z_scores = (both["gamma"] - both["gamma_true"]) / sigma.loc["gamma", "sigma"]
    # 5 cycles: every error within 3 sigma, and their spread consistent with sigma
    # (the RMS z-score of 5 unit normals exceeds 2 with probability ~0.1 %)
    assert np.all(np.abs(z_scores) < 3), z_scores.tolist()
    assert np.sqrt(np.mean(z_scores**2)) < 2
    # the rotation is the gear's 1/64 revolution per cycle
    np.testing.assert_allclose(both["gamma"].mean(), 2 * np.pi / 64, rtol=0.05)

"""Issue 6 Show 6 and issue 16: images -> localize -> calibrate/apply -> link -> rigid motion,
against the simulated gear's true motion in all six degrees of freedom, within the Monte Carlo
uncertainty."""

import numpy as np
import pandas as pd
from scipy.stats import norm

from latentz.cli.steps import track_tables
from latentz.localization import localize
from latentz.motion import motion_uncertainty

DOF = ["gamma", "beta", "alpha", "dx_nm", "dy_nm", "dz_nm"]


def test_six_degrees_of_freedom_agree_with_truth_within_uncertainty(
    small_microscope, small_calibration
):
    gear, cal = small_microscope.gear, small_calibration
    spots = localize(gear.frames, camera=gear.camera, roi_size=15)
    locs = cal.apply(spots[spots["converged"]])
    assert locs["in_range"].mean() > 0.9
    tables = track_tables(locs, n_sim=2000, seed=1)
    motion, tracks = tables["motion"], tables["tracks"]
    # each cycle against its own Monte Carlo standard deviation
    sigma = motion_uncertainty(tracks, motion, n_sim=2000, seed=1, per_transition=True)
    # the truth about the same point of the body as the measurement (the mean of all positions)
    both = motion.merge(gear.motion_of(tracks), on="frame", suffixes=("", "_true"))
    assert len(both) == gear.frames.shape[0] - 1
    both = both.merge(sigma, on="frame", suffixes=("", "_sigma"))
    err = np.column_stack([both[d] - both[f"{d}_true"] for d in DOF])
    err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
    z_scores = err / both[[f"{d}_sigma" for d in DOF]].to_numpy()
    # 5 cycles per degree of freedom: every error within the 0.1 % family-wise limit for 30
    # unit normals (4.15 sigma), each RMS z-score below 2 (RMS of 5 unit normals exceeds 2 with
    # probability ~0.1 %); the 30 pooled errors fall within 1 sigma 68 ± 17 % of the time
    # (2 binomial standard deviations)
    limit = norm.isf(0.001 / 2 / z_scores.size)
    assert np.all(np.abs(z_scores) < limit), z_scores.round(2).tolist()
    assert np.all(np.sqrt(np.mean(z_scores**2, axis=0)) < 2), z_scores.round(2).tolist()
    assert 0.51 <= np.mean(np.abs(z_scores) <= 1) <= 0.85, z_scores.round(2).tolist()
    # the rotation is the gear's 1/64 revolution per cycle
    np.testing.assert_allclose(both["gamma"].mean(), 2 * np.pi / 64, rtol=0.05)


def test_truth_and_measurement_share_the_centre_of_rotation(small_microscope):
    """Exact positions give exact translations: the truth is expressed about the same point of
    the body as the measurement, even though their coordinate systems differ by the gear's
    position in the field (about 25 µm here, so a mix-up would cost γ × 25 µm ≈ 2 µm)."""
    from latentz.motion import rigid_motion

    gear = small_microscope.gear
    truth = gear.truth[gear.truth["in_frame"]]
    pixel = gear.optics.pixel_size_nm
    tracks = truth.assign(
        x_nm=truth["field_x"] * pixel, y_nm=truth["field_y"] * pixel, z_nm=truth["z_nm"] + 500.0
    )
    motion = rigid_motion(tracks)
    expected = gear.motion_of(tracks)
    np.testing.assert_allclose(motion[DOF[3:]], expected[DOF[3:]], atol=1e-6)


def test_a_spurious_spot_pulls_truth_and_measurement_alike(small_microscope):
    """A tracked spot that matches no particle moves the measured centre of rotation; the truth
    follows it, so the translations still agree."""
    from latentz.motion import rigid_motion

    gear = small_microscope.gear
    truth = gear.truth[gear.truth["in_frame"]]
    pixel = gear.optics.pixel_size_nm
    tracks = truth.assign(x_nm=truth["field_x"] * pixel, y_nm=truth["field_y"] * pixel)
    ghost = tracks[tracks["frame"] == 1].iloc[:1].assign(particle=99, x=5.0, y=5.0)
    ghost = ghost.assign(x_nm=5.0 * pixel, y_nm=5.0 * pixel, z_nm=300.0)
    tracks = pd.concat([tracks, ghost], ignore_index=True)
    motion = rigid_motion(tracks)
    expected = gear.motion_of(tracks)
    np.testing.assert_allclose(motion[DOF[3:]], expected[DOF[3:]], atol=1e-6)

"""Tracking mode of localize (issue 14): same emitters and positions as full detection."""

import numpy as np
import pytest
import tifffile
from scipy.spatial import cKDTree

from latentz.localization import LOCALIZE_COLUMNS, localize
from latentz.simulate import gear_movie
from latentz.tracking import predict, rigid_step


@pytest.fixture(scope="module")
def gear():
    return gear_movie(quick=True, seed=3)


@pytest.fixture(scope="module")
def both(gear):
    full = localize(gear.frames, camera=gear.camera)
    tracked = localize(gear.frames, camera=gear.camera, track=True)
    return full, tracked


def test_rigid_step_recovers_a_known_rotation_and_shift():
    rng = np.random.default_rng(0)
    before = rng.uniform(0, 500, (12, 2))
    angle = 0.1
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    after = before @ rot.T + [3.0, -7.0]
    found_rot, shift, rms = rigid_step(before, after)
    np.testing.assert_allclose(found_rot, rot, atol=1e-12)
    np.testing.assert_allclose(shift, [3.0, -7.0], atol=1e-9)
    assert rms < 1e-9
    # a steady rotation is predicted exactly one step ahead
    np.testing.assert_allclose(predict(before, after), after @ rot.T + [3.0, -7.0], atol=1e-9)


def test_tracking_finds_the_emitters_of_full_detection_within_a_tenth_of_sigma(gear, both):
    full, tracked = both
    assert list(tracked.columns) == list(LOCALIZE_COLUMNS)
    # some frames were fitted from predictions (no detection score), not all re-detected
    assert tracked.snr.isna().sum() >= 10
    for t in range(gear.frames.shape[0]):
        a = full[(full.frame == t) & full.converged]
        b = tracked[(tracked.frame == t) & tracked.converged]
        assert len(a) == len(b) == gear.truth[(gear.truth.frame == t)].in_frame.sum()
        dist, idx = cKDTree(a[["x", "y"]].to_numpy()).query(b[["x", "y"]].to_numpy())
        assert len(set(idx)) == len(b)
        err = np.hypot(a.x_err.to_numpy()[idx], a.y_err.to_numpy()[idx])
        assert np.all(dist < 0.1 * err)


def test_tracking_a_tiff_path_reads_rois_and_matches_the_array(gear, both, tmp_path):
    _, tracked = both
    path = tmp_path / "gear.tif"
    tifffile.imwrite(path, gear.frames)
    from_file = localize(path, camera=gear.camera, track=True)
    np.testing.assert_allclose(from_file[["x", "y"]], tracked[["x", "y"]], atol=1e-9)

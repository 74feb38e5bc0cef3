"""Tracking mode of localize (issue 14): same emitters and positions as full detection."""

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy.spatial import cKDTree

from latentz.camera import Camera
from latentz.localization import LOCALIZE_COLUMNS, localize
from latentz.localization.follow import predict, rigid_step
from latentz.simulate import gear_movie, render_spots


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


@pytest.fixture(scope="module")
def ring():
    """8 point emitters turning on a ring of 45 px, 0.45 px per frame, rendered through the
    simulated microscope's pupil (not the fitted Gaussian), 30 frames of 128 x 128 px."""
    n_frames, n_spots = 30, 8
    angle = 2 * np.pi * np.arange(n_spots) / n_spots + 0.01 * np.arange(n_frames)[:, None]
    xy = 63.5 + 45.0 * np.stack([np.cos(angle), np.sin(angle)], axis=2)
    frame = np.repeat(np.arange(n_frames), n_spots)
    spots = pd.DataFrame({"frame": frame, "x": xy[..., 0].ravel(), "y": xy[..., 1].ravel()})
    spots["z_nm"] = 0.0
    frames, truth = render_spots(
        spots, frame_shape=(128, 128), photons=2e4, background=50.0, diameter_nm=0.0, seed=1
    )
    return frames, truth


def test_smooth_motion_is_detected_in_whole_frames_only_every_detect_every_frames(ring):
    # Noise maxima along the frame's edges (the band-pass's noise is 1.56x higher there) used to
    # seed tracks that were lost on the next frame, each loss forcing a whole-frame detection.
    frames, truth = ring
    full = localize(frames, camera=Camera())
    tracked = localize(frames, camera=Camera(), track=True, detect_every=10)
    assert set(tracked.frame[tracked.snr.notna()]) == {0, 10, 20}
    # every emitter in every frame, once, where full detection puts it (the simulated optics
    # shift the spots from their true positions, so full detection is the reference; its
    # second detections of one defocused spot are flagged duplicate)
    full = full[~full.duplicate]
    assert len(full) == len(tracked) == len(truth)
    assert full.converged.all() and tracked.converged.all()
    offsets = []
    for t in range(frames.shape[0]):
        a, b = full[full.frame == t], tracked[tracked.frame == t]
        dist, idx = cKDTree(a[["x", "y"]].to_numpy()).query(b[["x", "y"]].to_numpy())
        assert len(set(idx)) == len(b)
        offsets.append(dist / np.hypot(a.x_err.to_numpy()[idx], a.y_err.to_numpy()[idx]))
    offsets = np.concatenate(offsets)
    # Within a tenth of sigma where both modes fit the same ROI. A spot within a few hundredths
    # of a pixel of a pixel's edge may be fitted in ROIs one pixel apart, and the simulated
    # pupil's spot is no Gaussian: the fits then differ by up to about sigma (2 of 240 here).
    assert np.mean(offsets < 0.1) >= 0.97
    assert np.all(offsets < 1.0)

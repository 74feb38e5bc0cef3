"""`lz.localize(movie, calibration=cal)`: one call with the calibration's camera, ROI and method,
and the calibration applied; `localize` then `apply` warns when the ROI differs."""

import numpy as np
import pandas as pd
import pytest

import latentz as lz
from latentz._shared.sanity import LatentzWarning
from latentz.localization.quality import QUALITY_COLUMNS


def test_one_call_equals_localize_then_apply_with_the_calibrations_settings(
    small_microscope, small_calibration
):
    cal = small_calibration
    frames = small_microscope.gear.frames[:3]
    one = lz.localize(frames, calibration=cal)
    spots = lz.localize(frames, camera=cal.camera, roi_size=cal.roi_size, method=cal.method)
    two = cal.apply(spots)
    applied = [c for c in two.columns if c not in QUALITY_COLUMNS]
    pd.testing.assert_frame_equal(one[applied], two[applied])
    assert one["in_range"].mean() > 0.9 and np.isfinite(one["z_nm"]).mean() > 0.9


def test_arguments_override_the_calibration(small_microscope, small_calibration):
    cal = small_calibration
    frames = small_microscope.gear.frames[:1]
    brighter = lz.Camera(**{**cal.camera.as_dict(), "gain": 2 * cal.camera.gain})
    base = lz.localize(frames, calibration=cal)
    over = lz.localize(frames, calibration=cal, camera=brighter)
    # the gain scales the photons; the positions do not depend on it
    np.testing.assert_allclose(over["photons"].median() / base["photons"].median(), 2, rtol=0.05)


def test_apply_warns_when_the_roi_differs(small_microscope, small_calibration):
    cal = small_calibration
    frames = small_microscope.gear.frames[:1]
    other = cal.roi_size - 4
    spots = lz.localize(frames, camera=cal.camera, roi_size=other)
    message = f"{other} px ROI but the calibration in {cal.roi_size}"
    with pytest.warns(LatentzWarning, match=message):
        cal.apply(spots)


def test_calibration_must_be_a_calibration(small_microscope):
    with pytest.raises(TypeError, match="Calibration"):
        lz.localize(small_microscope.gear.frames[:1], calibration="cal.h5")


@pytest.mark.slow
def test_process_cluster_with_a_camera_and_a_calibration_gives_the_local_table(
    small_microscope, small_calibration
):
    # a TIFF path on worker processes: nothing may be computed through the client before the
    # tasks are built from the path (the lazy reader holds a lock that cannot be pickled)
    distributed = pytest.importorskip("distributed")
    assert small_calibration.camera is not None  # the camera comes with the calibration
    path = small_microscope.folder / "movie.tif"
    local = lz.localize(path, calibration=small_calibration, chunk_frames=2)
    with (
        distributed.LocalCluster(
            n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = lz.localize(path, calibration=small_calibration, scheduler=client, chunk_frames=2)
    assert len(local) > 0 and local["good"].any()
    pd.testing.assert_frame_equal(remote, local)


def test_a_calibration_roi_larger_than_the_frames_is_one_line_with_the_fix(
    small_microscope, small_calibration
):
    cal = small_calibration
    side = cal.roi_size - 4
    movie = small_microscope.gear.frames[:2]
    row, col = np.unravel_index(np.argmax(movie[0]), movie.shape[1:])  # a particle's image
    height, width = movie.shape[1:]
    r0 = int(np.clip(row - side // 2, 0, height - side))
    c0 = int(np.clip(col - side // 2, 0, width - side))
    frames = movie[:, r0 : r0 + side, c0 : c0 + side]
    with pytest.raises(ValueError) as caught:
        lz.localize(frames, calibration=cal)
    line = str(caught.value)
    assert "\n" not in line
    for part in (f"{cal.roi_size} px ROI", f"{side} x {side} px", f"roi_size={side}"):
        assert part in line, line
    # the way out it names works: a smaller ROI, with a warning that it is not the calibration's
    with pytest.warns(LatentzWarning, match="ROI"):
        lz.localize(frames, calibration=cal, roi_size=side)

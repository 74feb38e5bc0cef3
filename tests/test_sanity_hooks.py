"""The physical sanity checks fire at the API boundary, naming the value and the expected range,
and stay silent on consistent input."""

import warnings

import numpy as np
import pytest

from latentz._shared.sanity import LatentzWarning
from latentz.camera import Camera
from latentz.localization import localize


def test_offset_above_the_image_median_warns():
    frames = np.random.default_rng(0).poisson(50, (2, 64, 64)).astype(np.uint16)
    with pytest.warns(LatentzWarning, match="offset"):
        localize(frames, camera=Camera(offset=400.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        localize(frames, camera=Camera(offset=10.0))


def test_spot_widths_far_outside_the_calibration_warn(small_calibration):
    cal = small_calibration
    spots = cal.traces.planes(slice(10, 11))
    from latentz.calibration.traces import traces_table

    table = traces_table(spots)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        cal.apply(table)
    low, high = cal.width_range_px
    with pytest.warns(LatentzWarning, match=rf"calibrated {low:g}\.\.{high:g} px"):
        cal.apply(table.assign(wx=table["wx"] * 10))

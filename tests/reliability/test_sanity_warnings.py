"""Each physical sanity check warns, naming the value and the expected range; sane input
is silent."""

import warnings

import numpy as np
import pytest

from latentz._shared.sanity import (
    LatentzWarning,
    check_offset,
    check_pixel_size,
    check_widths,
    check_z_step,
)


def silent(func, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        func(*args, **kwargs)


def test_offset_above_median_warns():
    with pytest.warns(LatentzWarning, match=r"offset 500 ADU.*median 100 ADU.*<= 100"):
        check_offset(500.0, 100.0)
    silent(check_offset, 100.0, 120.0)


def test_pixel_size_mismatch_warns():
    with pytest.warns(LatentzWarning, match=r"Pixel size 65 nm.*108 nm; expected 106.92..109.08"):
        check_pixel_size(65.0, 108.0)
    silent(check_pixel_size, 108.0, 108.0)


def test_z_step_mismatch_warns():
    with pytest.warns(LatentzWarning, match=r"z step 1000 nm over 31 slices spans 30000 nm"):
        check_z_step(1000.0, 31, (-1500.0, 1500.0))
    silent(check_z_step, 100.0, 31, (-1500.0, 1500.0))


def test_widths_outside_calibration_warn():
    with pytest.warns(LatentzWarning, match=r"1 spot widths \(e.g. 9 px\).*expected 0.6..5 px"):
        check_widths(np.array([1.3, 1.5, 9.0, np.nan]), (1.2, 2.5))
    silent(check_widths, np.array([1.3, 2.4, np.nan]), (1.2, 2.5))

"""The smallest candidate ROI of `calibrate(roi_size=None)`: the smallest odd ROI that holds 95 %
of an in-focus spot's photons, checked by summing rendered Gaussians pixel by pixel."""

import numpy as np
import pytest

from latentz.calibration.roi import PHOTON_FRACTION, roi_for_width, roi_limit


def _held(width_px: float, roi: int) -> float:
    """Fraction of a centred Gaussian's photons inside a ``roi`` px square, by summing a
    10×-oversampled rendering over a field far larger than the spot."""
    half = 12 * width_px + roi
    step = 0.1
    grid = np.arange(-half, half + step / 2, step)
    profile = np.exp(-0.5 * (grid / width_px) ** 2)
    inside = np.abs(grid) <= roi / 2
    per_axis = profile[inside].sum() / profile.sum()
    return per_axis**2


@pytest.mark.parametrize("width", [0.9, 1.3, 2.0, 3.1, 4.4])
def test_roi_is_the_smallest_odd_square_holding_the_photon_fraction(width):
    roi = roi_for_width(width)
    assert roi % 2 == 1
    if roi > 7:  # above the floor, two pixels less would hold too little
        assert _held(width, roi - 2) < PHOTON_FRACTION
    assert _held(width, roi) >= PHOTON_FRACTION


def test_roi_limit_leaves_a_pixel_each_side():
    assert roi_limit((15, 15)) == 13 and roi_limit((21, 40)) == 19 and roi_limit((16, 16)) == 13


def test_bad_width_is_one_clear_error():
    with pytest.raises(ValueError, match="spot width"):
        roi_for_width(float("nan"))

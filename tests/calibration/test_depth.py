"""The depth of focus of width curves against their in-focus width (calibration.depth)."""

import numpy as np
import pytest

from latentz.calibration.depth import depth_ratio_per_nm


def _curve(z, sigma0, focus, depth):
    return sigma0 * np.sqrt(1 + ((z - focus) / depth) ** 2)


def test_ratio_of_exact_width_curves_is_their_median():
    z = np.arange(-750.0, 751.0, 10.0)
    curves = np.stack(
        [_curve(z, 150.0, -200.0, 250.0), _curve(z, 120.0, 180.0, 300.0), _curve(z, 100.0, 0, 90.0)]
    )
    curves[0, ::7] = np.nan  # planes that did not converge are left out
    expected = np.median([250 / 150**2, 300 / 120**2, 90 / 100**2])
    assert depth_ratio_per_nm(z, curves) == pytest.approx(expected, rel=1e-4)


def test_ratio_scales_with_the_z_step():
    # the same widths with every z 10x too large: d is 10x larger in those units
    z = np.arange(-750.0, 751.0, 10.0)
    curves = _curve(z, 140.0, 60.0, 220.0)[None]
    assert depth_ratio_per_nm(10 * z, curves) == pytest.approx(
        10 * depth_ratio_per_nm(z, curves), rel=1e-4
    )


def test_too_few_planes_give_nan():
    z = np.arange(5.0)
    assert np.isnan(depth_ratio_per_nm(z, _curve(z, 100.0, 2.0, 3.0)[None]))


def test_noise_is_not_a_width_curve():
    # a ROI on background: fits converge on a few planes only, with scattered widths
    rng = np.random.default_rng(0)
    z = np.arange(40) * 50.0
    widths = rng.uniform(36.0, 320.0, z.size)
    widths[rng.permutation(z.size)[:21]] = np.nan
    assert np.isnan(depth_ratio_per_nm(z, widths[None]))


def test_curve_focused_outside_the_planes_is_left_out():
    z = np.arange(-750.0, 751.0, 10.0)
    outside = _curve(z, 150.0, 2000.0, 250.0)  # only one flank: its focus is never imaged
    assert np.isnan(depth_ratio_per_nm(z, outside[None]))

"""Tilt plane: exact recovery, nutation and azimuth, degenerate input."""

import numpy as np
import pytest

from latentz.calibration.tilt import TiltPlane


def test_plane_nutation_azimuth_and_curvature_residuals():
    rng = np.random.default_rng(11)
    x, y = rng.uniform(0, 2.6e5, (2, 200))
    beta, azimuth = 2e-3, np.pi / 6
    # substrate normal leaning toward `azimuth`: the focus plane falls along that direction
    slope = np.tan(beta)
    curvature = 1e-9 * ((x - 1.3e5) ** 2 + (y - 1.3e5) ** 2)
    z = 50.0 - slope * (x * np.cos(azimuth) + y * np.sin(azimuth)) + curvature
    plane = TiltPlane.from_estimate(x, y, z - curvature)
    assert plane.nutation_mrad == pytest.approx(2.0, rel=1e-9)
    assert plane.azimuth_rad == pytest.approx(azimuth, abs=1e-9)
    np.testing.assert_allclose(plane.residuals(x, y, z), curvature, atol=1e-6)
    flat = TiltPlane.flat(3.0)
    assert flat.nutation_mrad == 0.0 and flat(1.0, 2.0) == 3.0


def test_mask_excludes_outliers():
    rng = np.random.default_rng(12)
    x, y = rng.uniform(0, 1e5, (2, 50))
    z = 1e-3 * x
    z[:3] += 500.0
    mask = np.ones(50, bool)
    mask[:3] = False
    assert TiltPlane.from_estimate(x, y, z, mask=mask).nutation_mrad == pytest.approx(1.0)


def test_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        TiltPlane.from_estimate([0.0, 1.0], [0.0, 1.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="collinear"):
        TiltPlane.from_estimate([0.0, 1.0, 2.0], [0.0, 1.0, 2.0], [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="one length"):
        TiltPlane.from_estimate([0.0, 1.0, 2.0], [0.0, 1.0], [0.0, 1.0, 2.0])

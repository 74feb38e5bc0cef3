"""Shape parameters: eqs. 4–6 and the auto pair, against analytic astigmatic images."""

import numpy as np
import pytest
from calib_synthetic import widths

from latentz.calibration.shape import (
    astigmatism_angle,
    ellipticity,
    reference_amplitude,
    shape_sigma,
    shape_value,
)

Z = np.arange(-3000.0, 3000.1, 50.0)


@pytest.mark.parametrize("theta", [np.pi / 4, 0.0, 0.3, -0.2])
def test_ellipticity_is_the_rotated_principal_ellipticity(theta):
    wx, wy, rho, s1, s2 = widths(Z, 0.0, theta=theta)
    e1, e2 = ellipticity(wx, wy, rho)
    e = (s1**2 - s2**2) / (s1**2 + s2**2)
    np.testing.assert_allclose(e1, e * np.cos(2 * theta), atol=1e-12)
    np.testing.assert_allclose(e2, e * np.sin(2 * theta), atol=1e-12)


@pytest.mark.parametrize("theta", [np.pi / 4, 0.0, 0.3, -0.1])
def test_astigmatism_angle_is_recovered_from_noisy_widths(theta):
    rng = np.random.default_rng(3)
    wx, wy, rho, *_ = widths(Z, 0.0, theta=theta)
    # 1 % width noise and 0.01 correlation noise, as a fit at ~10^4 photons gives
    wx = wx * (1 + 0.01 * rng.standard_normal(Z.size))
    wy = wy * (1 + 0.01 * rng.standard_normal(Z.size))
    rho = rho + 0.01 * rng.standard_normal(Z.size)
    # the angle of an ellipse of ellipticity e with noise δe is uncertain by about δe / (2 e);
    # far from focus e ~ 0.5, so the 121-plane estimate is good to well below 0.01 rad
    assert astigmatism_angle(wx, wy, rho) == pytest.approx(theta, abs=0.01)


def test_auto_pair_reduces_to_rho_w_and_rho_a_at_pi_over_4():
    wx, wy, rho, s1, s2 = widths(Z, 0.0, theta=np.pi / 4)
    amp = 1e4 / (2 * np.pi * s1 * s2)
    kw = {"theta": np.pi / 4}
    np.testing.assert_allclose(
        shape_value("auto", wx, wy, rho, **kw), shape_value("rho_w", wx, wy, rho), atol=1e-12
    )
    ref = reference_amplitude("rho_A", wx, wy, rho, amp)
    assert ref == amp[np.argmin(np.abs(rho))]
    assert reference_amplitude("auto_A", wx, wy, rho, amp, theta=np.pi / 4) == ref
    np.testing.assert_allclose(
        shape_value("auto_A", wx, wy, rho, amp, amplitude_ref=ref, **kw),
        shape_value("rho_A", wx, wy, rho, amp, amplitude_ref=ref),
        atol=1e-12,
    )
    # eq. 5: rho_A = rho / (A / A_ref)
    np.testing.assert_allclose(
        shape_value("rho_A", wx, wy, rho, amp, amplitude_ref=ref), rho * ref / amp
    )


def test_auto_carries_cylindrical_astigmatism_where_rho_is_zero():
    wx, wy, rho, *_ = widths(Z, 0.0, theta=0.0)
    assert np.max(np.abs(rho)) < 1e-12
    auto = shape_value("auto", wx, wy, rho, theta=0.0)
    # e1 (wx + wy) / 2 = (wx - wy)(wx + wy)^2 / (2 (wx^2 + wy^2)): strictly monotonic near focus
    near = np.abs(Z) <= 600
    assert np.all(np.diff(auto[near]) < 0) or np.all(np.diff(auto[near]) > 0)


def test_shape_sigma_matches_monte_carlo():
    rng = np.random.default_rng(4)
    wx, wy, rho, amp, ref = 1.8, 1.6, 0.25, 300.0, 340.0
    errors = (0.02, 0.015, 0.01, 4.0)
    n = 20000
    draws = [
        p + e * rng.standard_normal(n) for p, e in zip((wx, wy, rho, amp), errors, strict=True)
    ]
    for shape in ("rho", "rho_w", "rho_A", "auto", "auto_A"):
        mc = np.std(shape_value(shape, *draws, theta=0.3, amplitude_ref=ref))
        predicted = shape_sigma(shape, wx, wy, rho, amp, errors, theta=0.3, amplitude_ref=ref)
        # the sample SD of 20000 draws has a relative standard error of 1/sqrt(2n) = 0.5 %;
        # first-order propagation of 1 % errors adds well under 1 %
        assert predicted == pytest.approx(mc, rel=0.03), shape


def test_bad_input():
    with pytest.raises(ValueError, match="shape"):
        shape_value("sigma", 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="theta"):
        shape_value("auto", 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="amplitude_ref"):
        shape_value("rho_A", 1.0, 1.0, 0.0, 5.0)
    with pytest.raises(ValueError, match="round"):
        astigmatism_angle(np.ones(5), np.ones(5), np.zeros(5))
    with pytest.raises(ValueError, match="finite"):
        astigmatism_angle([np.nan], [1.0], [0.0])

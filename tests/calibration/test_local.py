"""Local models (z_f, Δx', Δy', z(shape), σ's) against analytic traces with known truth."""

import numpy as np
import pytest
from calib_synthetic import make_traces, widths
from numpy.polynomial import chebyshev as cheb

from latentz.calibration.local import LocalOptions, fit_local, sliding_rms
from latentz.calibration.shape import shape_value

SHAPES = ("rho", "rho_w", "rho_A")


def test_noise_free_traces_give_exact_focus_and_analytic_monotonic_range():
    traces, truth = make_traces(20, noise=0.0, seed=5)
    local = fit_local(traces, SHAPES)
    # A = N / (2 pi s1 s2) peaks at z_f exactly; an order-5 polynomial over the top half of this
    # peak misfits it slightly: the bias must stay far below the 10 nm the paper's use needs
    np.testing.assert_allclose(local.z_f, truth["z_f"], atol=2.0)
    assert local.in_focus.all()
    # rho = -2 u c / (c^2 + d^2 + u^2) is monotonic for |u| < sqrt(c^2 + d^2) = 1300 nm; the
    # range ends on the last plane (50 nm grid) before the slope changes sign
    bound = np.hypot(500.0, 1200.0)
    rng = local.shapes["rho"].z_range - truth["z_f"][:, None]
    assert np.all(np.abs(rng[:, 0] + bound) <= 50.0) and np.all(np.abs(rng[:, 1] - bound) <= 50)
    # dx is a cubic in z: the order-16 model reproduces it
    z = local.z_nm
    # Δx' is measured from the fitted z_f: the truth shifted by its slope (0.05 px/µm) times the
    # z_f error
    expected = truth["dx"] - 5e-5 * (local.z_f - truth["z_f"])[:, None]
    np.testing.assert_allclose(local.dx(z), expected, atol=1e-6)


def test_focus_scatter_matches_linear_error_propagation():
    n = 400
    traces, truth = make_traces(n, photons=20000.0, seed=6)
    local = fit_local(traces, ("rho",))
    err = local.z_f - truth["z_f"]
    # predicted SD of the peak of a least-squares polynomial: δz = −δA'(z_f) / A''(z_f), with
    # Var δA'(z_f) = σ_A² gᵀ (VᵀV)⁻¹ g over the fitted window (g the derivative of the basis)
    amp, sd = truth["true"]["amplitude"], truth["sd"]["amplitude"]
    win = amp >= 0.6 * amp.max(axis=1, keepdims=True)
    predicted = []
    for i in range(0, n, 40):
        zw = traces.z_nm[win[i]]
        lo, hi = zw.min(), zw.max()
        t = (2 * zw - lo - hi) / (hi - lo)
        v = cheb.chebvander(t, 5)
        tf = (2 * truth["z_f"][i] - lo - hi) / (hi - lo)
        g = cheb.chebvander(np.array([tf]), 4)[0] @ cheb.chebder(np.eye(6)) * 2 / (hi - lo)
        cov = np.linalg.inv(v.T @ v) * np.mean(sd[i, win[i]] ** 2)
        z_grid = truth["z_f"][i] + np.array([-1.0, 0.0, 1.0])
        s1 = widths(z_grid, truth["z_f"][i], theta=np.pi / 4)[3]
        s2 = widths(z_grid, truth["z_f"][i], theta=np.pi / 4)[4]
        a = 20000.0 / (2 * np.pi * s1 * s2)
        curvature = a[0] - 2 * a[1] + a[2]
        predicted.append(np.sqrt(g @ cov @ g) / abs(curvature))
    expected = np.mean(predicted)
    # the SD of 400 errors has a 3.5 % standard error; allow 20 % for the window's variation
    assert np.std(err) == pytest.approx(expected, rel=0.2)
    assert abs(np.mean(err)) < 4 * expected / np.sqrt(n)


def test_sigma_z_predicts_the_error_of_localizing_independent_emitters():
    # test emitters independent of the calibration particles (other positions, other heights:
    # their own z_f) imaged through the same microscope; the residual-based σ_z(z) of each
    # calibration particle must predict the z error of the emitter localized with its models
    # (paper Fig. 2 e–f). The emitters are as bright as the calibration particles, so ρ_A uses
    # the calibration particle's amplitude reference (latentz's default).
    traces, truth = make_traces(60, photons=20000.0, seed=7)
    test, test_truth = make_traces(60, photons=20000.0, seed=70)
    assert np.all(test_truth["z_f"] != truth["z_f"])
    local = fit_local(traces, SHAPES)
    # the emitter's true z measured from its own focus, on the calibration particle's axis
    z_true = traces.z_nm[None, :] - test_truth["z_f"][:, None] + local.z_f[:, None]
    near = np.abs(z_true - local.z_f[:, None]) < 1500
    for shape in ("rho_w", "rho_A"):
        model = local.shapes[shape]
        ref = model.amplitude_ref[:, None]
        s = shape_value(
            shape, test["wx"], test["wy"], test["rho"], test["amplitude"], amplitude_ref=ref
        )
        inside = model.inverse.contains(s) & near
        err = np.where(inside, model.inverse(s) - z_true, np.nan)
        ratio = np.sqrt(
            np.nanmean(err**2) / np.nanmean(np.where(inside, model.sigma_z, np.nan) ** 2)
        )
        # ~3600 test images: the RMS has a 1.2 % sampling error; the calibration polynomial's
        # own error adds about sqrt(k/m) ~ 0.37 in quadrature (7 % in RMS)
        assert 0.9 < ratio < 1.2, (shape, ratio)


def test_lateral_models_and_their_sigmas():
    traces, truth = make_traces(100, photons=20000.0, seed=8)
    local = fit_local(traces, ("rho",))
    z = local.z_nm
    zf = truth["z_f"][:, None]
    for model, sigma, true, sd in (
        (local.dx, local.sigma_dx, truth["dx"], truth["sd"]["x"]),
        (local.dy, local.sigma_dy, truth["dy"], truth["sd"]["y"]),
    ):
        # Δ(z) = x'(z) − x'(z_f): the truth shifted by its own value at the fitted z_f
        slope_f = np.gradient(true, traces.z_nm, axis=1)[:, 60:61]
        expected = true - (local.z_f[:, None] - zf) * slope_f
        k, m = 17, z.shape[1]
        bound = 4 * np.sqrt(k / m) * np.mean(sd)  # 4 standard errors of the fitted curve
        assert np.sqrt(np.mean((model(z) - expected) ** 2)) < bound
        rms = np.sqrt(np.nanmean(sigma**2))
        # 100 x 121 residuals: the RMS has a sampling error of 0.6 %; the sliding window's
        # edge planes see fewer residuals, so allow 5 %
        assert rms == pytest.approx(np.sqrt(np.mean(sd**2)), rel=0.05)


def test_sliding_rms_of_gaussian_noise():
    rng = np.random.default_rng(9)
    z = np.broadcast_to(np.arange(0.0, 4000.0, 10.0), (50, 400))
    r = 3.0 * rng.standard_normal(z.shape)
    out = sliding_rms(z, r, window_nm=500.0, n_params=0)
    assert np.mean(out) == pytest.approx(3.0, rel=0.01)
    r[:, :10] = np.nan
    assert np.isnan(sliding_rms(z, r, window_nm=500.0, n_params=0)[:, :10]).all()


def test_short_monotonic_range_is_invalid():
    traces, _ = make_traces(3, noise=0.0, seed=10)
    local = fit_local(traces, ("rho",), options=LocalOptions(min_range_nm=5000.0))
    assert not local.shapes["rho"].inverse.valid.any()


def test_models_stop_at_a_gap_of_unmeasured_planes():
    """A particle whose fits failed on 7 planes near the top of its stack, with one measured
    plane beyond: its models must not reach across the gap (an order-16 polynomial is
    unconstrained there), so its monotonic range ends before it and Δx' holds the truth
    wherever z is in range."""
    traces, truth = make_traces(6, noise=0.0, seed=5)
    z = traces.z_nm
    gap = (z > 900.0) & (z < 1300.0)
    for name in ("x", "y", "wx", "wy", "rho", "amplitude"):
        traces.data[name][:, gap] = np.nan
    local = fit_local(traces, ("rho",))
    top = z[gap].min()
    assert np.all(local.shapes["rho"].z_range[:, 1] < top)
    inside = (z[None, :] >= local.shapes["rho"].z_range[:, :1]) & (
        z[None, :] <= local.shapes["rho"].z_range[:, 1:]
    )
    expected = truth["dx"] - 5e-5 * (local.z_f - truth["z_f"])[:, None]
    error = np.where(inside, local.dx(local.z_nm) - expected, 0.0)
    # noise-free: the cubic truth is reproduced to numerical precision where the model holds
    np.testing.assert_allclose(error, 0.0, atol=1e-6)


def test_focus_under_strong_astigmatism_lies_between_the_line_foci():
    """Astigmatism strong enough that A(z) peaks at both line foci (±450 nm about the centre,
    300 nm depth of focus), the + side a little brighter by a slope k that varies between
    particles, from none (equal peaks) to 10 %/µm. The window about the maximum spans both
    peaks, and its polynomial's peak falls at either focus or at its edge. Best focus must be
    interior for every particle and lie midway between the two peaks of its own A(z) (found
    here on a fine grid of the analytic A), where a single peak lies under weaker astigmatism."""
    from latentz.calibration.local import best_focus

    n, c, d = 12, 450.0, 300.0
    rng = np.random.default_rng(3)
    centre, k = rng.uniform(-100.0, 100.0, n), np.linspace(0.0, 0.1, n)
    z = np.broadcast_to(np.arange(-1500.0, 1500.1, 20.0), (n, 151)).copy()

    def amplitude(u: np.ndarray, slope: np.ndarray) -> np.ndarray:
        wx, wy = np.sqrt(1 + ((u - c) / d) ** 2), np.sqrt(1 + ((u + c) / d) ** 2)
        return 1e4 / (wx * wy) * (1 + slope * u / 1000.0)

    traces = amplitude(z - centre[:, None], k[:, None])
    traces *= 1 + 0.003 * rng.standard_normal(traces.shape)  # a bright bead's amplitude noise
    u = np.linspace(0.0, 1200.0, 120001)
    plus = np.array([u[np.argmax(amplitude(u, s))] for s in k])
    minus = np.array([-u[np.argmax(amplitude(-u, s))] for s in k])
    _, z_f, interior = best_focus(z, traces)
    assert interior.all()
    np.testing.assert_allclose(z_f - centre, (plus + minus) / 2, atol=15.0)

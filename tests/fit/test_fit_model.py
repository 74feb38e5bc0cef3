"""Eq. 1, its derivatives and its Cramér–Rao bounds against analytic results."""

import math

import numpy as np
import pandas as pd
import pytest
from fit_truth import noisy_rois, truth_table

from latentz.fit import (
    PARAMS,
    _kernels,
    amplitude_of,
    crlb,
    fisher_information,
    moment_start,
    photons_of,
    render_rois,
)
from latentz.fit._model import as_param_array, covariance, model_and_jacobian
from latentz.fit.api import starts_at_peaks


def _one(**kw):
    base = dict(x=10.0, y=10.0, amplitude=100.0, background=5.0, wx=1.5, wy=1.5, rho=0.0)
    base.update(kw)
    return pd.DataFrame({k: [v] for k, v in base.items()})


def test_render_samples_eq1_at_pixel_centres():
    table = _one(x=3.0, y=2.0, wx=1.2, wy=0.8, rho=0.4)
    roi = render_rois(table, shape=(5, 7))[0]
    # pixel [i, j] is at x = j, y = i
    assert roi[2, 3] == pytest.approx(105.0)
    u, v = (4 - 3.0) / 1.2, (1 - 2.0) / 0.8
    q = (u * u - 2 * 0.4 * u * v + v * v) / (1 - 0.4**2)
    assert roi[1, 4] == pytest.approx(100.0 * np.exp(-q / 2) + 5.0, rel=1e-14)


def test_sum_of_a_well_sampled_spot_is_its_photons():
    # The Poisson summation formula: sampling a Gaussian of sd >= 1 px at integer points sums
    # to its integral within 2 exp(-2 pi^2 w^2) < 1e-8 of it.
    table = _one(wx=1.3, wy=2.1, rho=-0.5, background=0.0, x=30.2, y=29.7)
    roi = render_rois(table, shape=61)[0]
    photons = photons_of(100.0, 1.3, 2.1, -0.5)
    assert roi.sum() == pytest.approx(photons, rel=1e-8)
    assert amplitude_of(photons, 1.3, 2.1, -0.5) == pytest.approx(100.0)


def test_photons_can_replace_amplitude_in_the_table():
    table = _one(wx=1.1, rho=0.3).drop(columns="amplitude").assign(photons=2000.0)
    roi = render_rois(table, shape=41)[0]
    assert roi.sum() - 5.0 * 41 * 41 == pytest.approx(2000.0, rel=1e-8)


def test_jacobian_matches_central_differences():
    params = np.array([[4.3, 5.6, 80.0, 7.0, 1.4, 2.2, -0.35]])
    _, jac = model_and_jacobian(params, (11, 11))
    internal = np.array([4.3, 5.6, 80.0, 7.0, np.log(1.4), np.log(2.2), np.arctanh(-0.35)])

    def model(p):
        nat = np.array([[*p[:4], np.exp(p[4]), np.exp(p[5]), np.tanh(p[6])]])
        return model_and_jacobian(nat, (11, 11))[0][0]

    for k in range(7):
        step = np.zeros(7)
        step[k] = 1e-6
        numeric = (model(internal + step) - model(internal - step)) / 2e-6
        np.testing.assert_allclose(jac[0, :, k], numeric, rtol=1e-6, atol=1e-7)


def test_crlb_of_a_centred_round_spot_without_background_is_w_over_sqrt_n():
    # Without background and with rho = 0 the position decouples from every other parameter
    # (odd integrands), so var(x) = 1 / sum (d mu/dx)^2 / mu = w^2 / N exactly.
    table = _one(background=1e-12, wx=1.7, wy=1.7, x=20.0, y=20.0, amplitude=500.0)
    bound = crlb(table, shape=41)[0]
    n = photons_of(500.0, 1.7, 1.7, 0.0)
    assert bound[0] == pytest.approx(1.7 / np.sqrt(n), rel=1e-6)
    assert bound[1] == pytest.approx(1.7 / np.sqrt(n), rel=1e-6)


def test_read_noise_and_background_raise_the_bound():
    table = _one()
    plain = crlb(table, shape=15)[0]
    noisy = crlb(table, shape=15, readnoise=3.0)[0]
    assert np.all(noisy > plain)
    info = fisher_information(table, shape=15)[0]
    np.testing.assert_allclose(info, info.T)
    assert np.all(np.linalg.eigvalsh(info) > 0)


def test_covariance_kernel_inverts_the_numpy_fisher_information():
    table = as_param_array(truth_table(200, 15, seed=6))
    table[0, 2] = 0.0  # no spot: the position is not identifiable, the information singular
    info = fisher_information(table, shape=15, readnoise=1.5)
    cov = covariance(table, shape=15, readnoise=1.5)
    assert np.all(np.isnan(cov[0]))
    expected = np.linalg.inv(info[1:])
    sd = np.sqrt(np.diagonal(expected, 0, 1, 2))
    # each entry relative to its variances (off-diagonal entries can be near zero)
    np.testing.assert_allclose(
        cov[1:] / (sd[:, :, None] * sd[:, None, :]),
        expected / (sd[:, :, None] * sd[:, None, :]),
        rtol=0,
        atol=1e-9,
    )


def test_kernel_start_is_the_twin_of_moment_start():
    table = truth_table(300, 11, seed=4)
    rois = noisy_rois(table, 11, seed=5)
    rois[0] = 0.0
    expected = moment_start(rois)
    got = np.empty_like(expected)
    for k, roi in enumerate(rois):
        _kernels._start(roi, got[k])
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)
    # the start is already within a pixel of the truth for these well-separated spots
    assert np.median(np.hypot(expected[:, 0] - table.x, expected[:, 1] - table.y)) < 0.5


def test_a_start_at_a_given_peak_stays_off_a_brighter_neighbour():
    """ROIs of 15 px with a spot near the centre and one 3x brighter 5 px to its right: the plain
    moment start goes to the bright spot; the start at the centre spot's pixel lies within a
    pixel of it, and the kernels (`starts_at_peaks`) give what the NumPy twin gives."""
    table = truth_table(200, 15, seed=6, photons=(1e3, 1e4), wmax=1.6)
    bright = table.assign(x=table.x + 5.0, amplitude=3 * table.amplitude, background=0.0)
    rois = noisy_rois(table, 15, seed=7) + noisy_rois(bright, 15, seed=8)
    peaks = np.column_stack([np.rint(table.y), np.rint(table.x)]).astype(int)
    expected = moment_start(rois, peaks)
    np.testing.assert_allclose(starts_at_peaks(rois, peaks), expected, rtol=1e-10, atol=1e-10)
    assert np.all(np.hypot(expected[:, 0] - table.x, expected[:, 1] - table.y) < 1.0)
    plain = moment_start(rois)
    assert np.all(np.hypot(plain[:, 0] - bright.x, plain[:, 1] - bright.y) < 1.0)


@pytest.mark.parametrize(
    ("params", "shape", "match"),
    [
        (np.zeros((2, 6)), 5, "shape"),
        (pd.DataFrame({"x": [1.0]}), 5, "missing"),
        (_one(wx=0.0), 5, "wx, wy > 0"),
        (_one(rho=1.0), 5, r"\|rho\| < 1"),
        (_one(), (0, 4), "shape"),
    ],
)
def test_render_rejects_bad_input(params, shape, match):
    with pytest.raises(ValueError, match=match):
        render_rois(params, shape=shape)


def test_params_order_is_eq1s():
    assert PARAMS == ("x", "y", "amplitude", "background", "wx", "wy", "rho")


def test_fast_log_factorial_matches_lgamma():
    from latentz.fit._kernels import log_factorial

    values = np.concatenate([np.linspace(1e-9, 20, 4001), np.geomspace(20, 1e7, 500), [0.0]])
    got = np.array([log_factorial(v) for v in values])
    want = np.array([math.lgamma(v + 1.0) for v in values])
    # Stirling's series truncated at z^-7 (error < 1e-11) plus float64 rounding of large values
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-10)


@pytest.mark.parametrize(
    "natural",
    [
        (7.3, 6.8, 500.0, 20.0, 1.4, 2.1, 0.5),  # every row by the recurrence
        (0.2, 14.6, 500.0, 20.0, 0.3, 0.35, -0.9),  # narrow, in a corner: rows computed directly
        (0.0, 7.0, 500.0, 20.0, 0.443, 0.35, 0.0),  # rows 0-2 and 12-14 directly, the rest not
    ],
)
def test_kernel_model_and_fisher_matrix_are_eq1s(natural):
    shape = (15, 15)
    theta = np.array([natural])
    mu, jac = model_and_jacobian(theta, shape)
    internal = np.array([*natural[:4], math.log(natural[4]), math.log(natural[5])])
    internal = np.append(internal, math.atanh(natural[6]))
    roi = np.random.default_rng(5).poisson(mu[0]).reshape(shape).astype(float)
    mu_k, w_k = np.empty(mu.size), np.empty(mu.size)
    hess, grad = np.empty((7, 7)), np.empty(7)
    obj = _kernels._evaluate(
        roi, internal, _kernels.MLE, 0.0, 1.0, mu_k, w_k, mu_k, w_k, hess, grad
    )
    assert obj == (0.0, 0.0)  # the MLE objective is the deviance change from the reference
    np.testing.assert_allclose(mu_k, mu[0], rtol=1e-12)
    weights = 1.0 / mu[0]
    fisher = jac[0].T @ (weights[:, None] * jac[0])
    score = jac[0].T @ (roi.ravel() * weights - 1.0)
    # float64 rounding, relative to the largest term (entries that vanish by symmetry included)
    np.testing.assert_allclose(hess, fisher, rtol=1e-10, atol=1e-12 * np.abs(fisher).max())
    np.testing.assert_allclose(grad, score, rtol=1e-9, atol=1e-12 * np.abs(jac).max() * roi.max())


def test_kernel_log_likelihood_and_log_ratio_match_lgamma_and_log():
    rng = np.random.default_rng(3)
    # counts from empty to 10^6 (the log of the product of 300 large counts overflows float64)
    roi = np.concatenate([[0.0, -1.0, 0.3, 5.0, 7.99, 8.0], 10 ** rng.uniform(0, 6, 300)])
    roi = roi.reshape(1, -1)
    mu = roi.ravel() * rng.uniform(0.5, 2.0, roi.size) + 1.0
    s2 = 2.25
    m, d = mu + s2, roi.ravel() + s2
    want = sum(
        dk * math.log(mk) - mk - math.lgamma(dk + 1.0) if dk > 0 else -mk
        for dk, mk in zip(d, m, strict=True)
    )
    got = _kernels._log_likelihood(roi, mu, 1.0 / m, s2)
    # Stirling's series truncated at d^-7 (error < 1e-11 per pixel) and float64 rounding
    assert abs(got - want) < 1e-12 * np.sum(np.abs(d * np.log(m))) + 1e-9
    old = 10 ** rng.uniform(-2, 6, 2000)
    new = old * np.exp(rng.uniform(-0.5, 0.5, old.size))
    ratio = np.array([_kernels._log_ratio(a, b, 1.0 / b) for a, b in zip(new, old, strict=True)])
    np.testing.assert_allclose(ratio, np.log(new / old), rtol=1e-12, atol=1e-15)

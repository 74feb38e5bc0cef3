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
from latentz.fit._model import model_and_jacobian


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

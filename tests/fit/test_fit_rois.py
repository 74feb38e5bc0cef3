"""fit_rois / fit_arrays: exact recovery, the NumPy twin, the camera path, flags and bad input."""

import math

import numpy as np
import pandas as pd
import pytest
from fit_truth import noisy_rois, truth_table

from latentz.camera import Camera
from latentz.fit import FIT_COLUMNS, METHODS, PARAMS, crlb, fit_arrays, fit_rois, render_rois
from latentz.fit._reference import fit_reference
from latentz.fit.api import parameter_bounds
from latentz.fit.robust import misspecified_errors

DESIGN_COLUMNS = [
    "x", "y", "amplitude", "background", "wx", "wy", "rho", "photons",
    "x_err", "y_err", "amplitude_err", "background_err", "wx_err", "wy_err", "rho_err",
    "loglik", "chi2", "iterations", "converged",
    # added after the design's list: the correlations of the shape's parameters
    "amplitude_wx_corr", "amplitude_wy_corr", "amplitude_rho_corr", "wx_wy_corr", "wx_rho_corr",
    "wy_rho_corr",
]  # fmt: skip


def test_columns_are_the_design_contract():
    table = truth_table(3, 11, seed=0)
    fit = fit_rois(noisy_rois(table, 11, seed=1))
    assert list(fit.columns) == DESIGN_COLUMNS == list(FIT_COLUMNS)
    np.testing.assert_allclose(
        fit.photons, 2 * np.pi * fit.amplitude * fit.wx * fit.wy * np.sqrt(1 - fit.rho**2)
    )


@pytest.mark.parametrize("method", list(METHODS))
def test_noise_free_rois_are_recovered_exactly(method):
    table = truth_table(50, 15, seed=7, wmax=2.5)
    rois = render_rois(table, shape=15)
    truth = table[list(PARAMS)].to_numpy()
    bound = crlb(truth, shape=15)
    # Converged means that the next step is at most tol (default 0.01) bounds long, i.e. the fit
    # is within about tol bounds of the optimum (here the truth).
    fit = fit_rois(rois, method=method)
    assert fit.converged.all()
    err = np.abs(fit[list(PARAMS)].to_numpy() - truth) / bound
    assert np.all(err < 1e-2)
    exact = fit_rois(rois, method=method, tol=1e-10)
    assert exact.converged.all()
    # float64 rounding of the objective limits this to about 1e-7
    np.testing.assert_allclose(exact[list(PARAMS)].to_numpy(), truth, rtol=1e-6, atol=1e-6)
    assert np.all(exact.chi2 < 1e-10)


@pytest.mark.parametrize("method", list(METHODS))
def test_kernel_matches_its_numpy_twin(method):
    table = truth_table(40, 9, seed=11, wmax=2.0)
    rois = noisy_rois(table, 9, seed=12) + np.random.default_rng(13).normal(0, 1.5, (40, 9, 9))
    rois[3, 4, 4] = np.nan
    rois[4] = 0.0
    got = fit_arrays(rois, method=method, readnoise=1.5, errors="sandwich")
    lower, upper = parameter_bounds((9, 9), 1.5)
    want = fit_reference(rois, method=METHODS[method], s2=1.5**2, lower=lower, upper=upper)
    if method != "lsq":  # the reported errors are the sandwich's, the bound where it fails
        sandwich = misspecified_errors(rois, want[0], readnoise=1.5)
        usable = np.all(np.isfinite(sandwich), axis=1)
        assert usable.sum() >= 35
        want = (want[0], np.where(usable[:, None], sandwich, want[1]), *want[2:])
    for name, a, b in zip(got._fields[:-1], got[:-1], want, strict=True):
        np.testing.assert_allclose(
            np.asarray(a, float), np.asarray(b, float), rtol=1e-8, atol=1e-8, err_msg=name
        )


def test_wlsq_reaches_the_poisson_mle():
    # light-weighting's fixed point solves the Poisson score equations: same estimate
    table = truth_table(500, 15, seed=21)
    rois = noisy_rois(table, 15, seed=22)
    mle = fit_arrays(rois, method="mle", tol=1e-5)
    wlsq = fit_arrays(rois, method="wlsq", tol=1e-5)
    ok = mle.converged & wlsq.converged
    assert ok.mean() > 0.99
    assert np.all(np.abs(mle.params - wlsq.params)[ok] < 1e-4 * mle.errors[ok])


def test_camera_rois_in_adu_match_photons_with_read_noise():
    cam = Camera(offset=100.0, gain=0.5, readnoise=2.0)
    table = truth_table(2000, 15, seed=31, wmax=2.5)
    rng = np.random.default_rng(32)
    photons = noisy_rois(table, 15, seed=33) + rng.normal(0.0, 2.0, (2000, 15, 15))
    fit = fit_rois(cam.to_adu(photons), camera=cam)
    direct = fit_arrays(photons, readnoise=2.0)
    np.testing.assert_allclose(fit[list(PARAMS)].to_numpy(), direct.params, rtol=1e-9, atol=1e-9)
    truth = table[list(PARAMS)].to_numpy()
    z = (direct.params - truth) / crlb(truth, shape=15, readnoise=2.0)
    # the mu + s^2 approximation of read noise keeps the spread at the bound (sampling 0.016)
    assert np.all(np.abs(z[direct.converged, :2].std(axis=0) - 1) < 0.05)


def test_init_from_the_truth_gives_the_same_fit_as_the_moment_start():
    table = truth_table(300, 15, seed=41)
    rois = noisy_rois(table, 15, seed=42)
    init = table[list(PARAMS)].copy()
    init.iloc[0, 0] = np.nan  # falls back to the moment start
    a = fit_arrays(rois, tol=1e-5)
    b = fit_arrays(rois, init=init, tol=1e-5)
    ok = a.converged & b.converged
    assert ok.mean() > 0.99
    assert np.all(np.abs(a.params - b.params)[ok] < 1e-3 * a.errors[ok])


def test_iteration_limit_flags_but_keeps_finite_values():
    table = truth_table(100, 11, seed=51)
    result = fit_arrays(noisy_rois(table, 11, seed=52), max_iter=1)
    assert not result.converged.any()
    assert np.all(result.iterations == 1)
    assert np.all(np.isfinite(result.params))


def test_non_finite_roi_is_flagged_and_the_others_are_unaffected():
    table = truth_table(20, 11, seed=61)
    rois = noisy_rois(table, 11, seed=62)
    clean = fit_arrays(rois)
    rois[5, 0, 0] = np.nan
    rois[9, 3, 3] = np.inf
    dirty = fit_arrays(rois)
    bad = np.zeros(20, dtype=bool)
    bad[[5, 9]] = True
    assert not dirty.converged[bad].any()
    assert np.all(dirty.iterations[bad] == 0)
    assert np.all(np.isnan(dirty.params[bad]))
    for a, b in zip(clean, dirty, strict=True):
        np.testing.assert_array_equal(np.asarray(a)[~bad], np.asarray(b)[~bad])


@pytest.mark.parametrize("method", list(METHODS))
def test_blank_and_saturated_rois_do_not_crash_the_batch(method):
    table = truth_table(4, 11, seed=71)
    rois = noisy_rois(table, 11, seed=72)
    rois[0] = 0.0
    rois[1] = 65535.0
    rois[2, 3:8, 3:8] = 65535.0  # a clipped spot
    fit = fit_rois(rois, method=method, camera=None)
    assert len(fit) == 4
    assert not fit.converged[0]  # no spot: the amplitude sits on its bound
    assert not fit.converged[1]
    assert fit.converged[3]
    numeric = fit.drop(columns="converged").to_numpy(dtype=float)
    assert np.all(np.isfinite(numeric[:, :7]))


@pytest.mark.parametrize(
    ("rois", "kwargs", "error", "match"),
    [
        (np.zeros((5, 5)), {}, ValueError, "3 dimensions"),
        (np.zeros((1, 2, 5, 5)), {}, ValueError, "3 dimensions"),
        (np.zeros((0, 5, 5)), {}, ValueError, "non-empty"),
        (np.zeros((3, 2, 5)), {}, ValueError, "at least 3 x 3"),
        (np.array([[["a"]]]), {}, TypeError, "numeric dtype"),
        (np.ones((2, 5, 5)), {"method": "ls"}, ValueError, "method"),
        (np.ones((2, 5, 5)), {"max_iter": 0}, ValueError, "max_iter"),
        (np.ones((2, 5, 5)), {"tol": -1.0}, ValueError, "tol"),
        (np.ones((2, 5, 5)), {"init": np.zeros((3, 7))}, ValueError, "init"),
        (np.ones((2, 5, 5)), {"init": np.zeros((2, 6))}, ValueError, "init"),
        (np.ones((2, 5, 5)), {"camera": "cam"}, TypeError, "Camera"),
        (
            np.ones((2, 5, 5)),
            {"camera": Camera(flatfield=np.ones((5, 5)))},
            ValueError,
            "flatfield",
        ),
    ],
)
def test_bad_input_raises_clearly(rois, kwargs, error, match):
    with pytest.raises(error, match=match):
        fit_rois(rois, **kwargs)


def test_negative_read_noise_is_refused():
    with pytest.raises(ValueError, match="readnoise"):
        fit_arrays(np.ones((1, 5, 5)), readnoise=-1.0)


def test_iterations_are_few_from_the_moment_start():
    table = truth_table(1000, 11, seed=81, wmax=2.0)
    result = fit_arrays(noisy_rois(table, 11, seed=82))
    assert result.converged.all()
    assert np.median(result.iterations) <= 6
    assert math.isclose(float(pd.Series(result.iterations).max()), result.iterations.max())


def test_crlb_errors_on_request_and_a_clear_error_for_another_choice():
    table = truth_table(20, 11, seed=31)
    rois = noisy_rois(table, 11, seed=32)
    fit = fit_arrays(rois, errors="crlb", tol=1e-8)  # the bound at the last iterate
    ok = fit.converged
    np.testing.assert_allclose(fit.errors[ok], crlb(fit.params[ok], shape=11), rtol=1e-6)
    assert np.isnan(fit.correlations).all()
    with pytest.raises(ValueError, match="errors"):
        fit_arrays(rois, errors="fisher")


def test_the_default_tol_ends_within_about_a_hundredth_of_a_bound_of_the_optimum():
    # tol = 0.01: the fit stops when the next step, or the step after an unevaluated last one
    # (estimated from how much the last step shrank), is at most 0.01 bounds long
    table = truth_table(2000, 11, seed=51)
    rois = noisy_rois(table, 11, seed=52)
    fit = fit_arrays(rois)
    optimum = fit_arrays(rois, tol=1e-6)
    ok = fit.converged & optimum.converged
    assert ok.mean() > 0.99
    distance = np.abs(fit.params - optimum.params)[ok] / optimum.errors[ok]
    assert np.quantile(distance, 0.99) < 0.02
    assert distance.max() < 0.05

"""Show 1–2 of the fitting issue: bias, precision at the Cramér–Rao bound, convergence.

10^4 ROIs from eq. 1 with Poisson noise: sub-pixel positions, rho in [-0.6, 0.6], wx and wy in
[1, 3] px, 10^3 to 10^5 photons (log-uniform), background 10–100 photons/px. The ROIs are 21 x 21
px: a 3 px wide spot then keeps 3.3 standard deviations on each side, so the background is
measured and the test is not about a truncated model (a smaller ROI only raises the bound).

Tolerances: the standard deviation of z = error / bound over n ROIs has a sampling error of about
1 / sqrt(2 n) (0.007 for n = 10^4, 0.01 per photon decade), well inside the issue's 1.05 / 1.10
limits; the mean error of x and y must also be within 5 standard errors of zero.
"""

import numpy as np
import pytest
from fit_truth import noisy_rois, truth_table

from latentz.fit import PARAMS, crlb, fit_arrays

N, SIZE = 10_000, 21
LIMIT = {"mle": 1.05, "wlsq": 1.10}


@pytest.fixture(scope="module")
def data():
    table = truth_table(N, SIZE, seed=2021)
    rois = noisy_rois(table, SIZE, seed=3925)
    truth = table[list(PARAMS)].to_numpy()
    return table, rois, truth, crlb(truth, shape=SIZE)


@pytest.fixture(scope="module", params=["mle", "wlsq"])
def fitted(request, data):
    table, rois, truth, bound = data
    return request.param, fit_arrays(rois, method=request.param)


def test_convergence_and_no_gross_failures(data, fitted):
    _, _, truth, bound = data
    _, result = fitted
    assert result.converged.mean() >= 0.995
    z = (result.params - truth) / bound
    gross = np.any(np.abs(z[:, :2]) > 5, axis=1)
    assert gross.mean() <= 1e-4
    assert np.all(np.isfinite(result.params))


def test_bias_is_below_the_issue_limits(data, fitted):
    _, _, truth, bound = data
    _, result = fitted
    ok = result.converged
    err = (result.params - truth)[ok]
    assert np.all(np.abs(err[:, :2].mean(axis=0)) < 0.01)
    assert abs(err[:, 6].mean()) < 0.005
    standard_error = err[:, :2].std(axis=0) / np.sqrt(ok.sum())
    assert np.all(np.abs(err[:, :2].mean(axis=0)) < 5 * standard_error)


@pytest.mark.parametrize("decade", [(1e3, 1e4), (1e4, 1e5), (1e3, 1e5)])
def test_spread_is_at_the_cramer_rao_bound_across_the_photon_range(data, fitted, decade):
    table, _, truth, bound = data
    method, result = fitted
    sel = result.converged & table.photons.between(*decade).to_numpy()
    z = ((result.params - truth) / bound)[sel]
    spread = z.std(axis=0)
    # never below the bound by more than sampling error, never above the issue's limit
    tolerance = 4 / np.sqrt(2 * sel.sum())
    assert np.all(spread <= LIMIT[method]), dict(zip(PARAMS, spread.round(3), strict=True))
    assert np.all(spread >= 1 - tolerance), dict(zip(PARAMS, spread.round(3), strict=True))


def test_reported_errors_are_the_bound_at_the_fit(data, fitted):
    _, _, _, bound = data
    _, result = fitted
    ratio = result.errors[result.converged] / bound[result.converged]
    # the bound at the fitted parameters scatters around the bound at the truth
    assert np.all(np.abs(np.median(ratio, axis=0) - 1) < 0.02)


def test_least_squares_is_unbiased_but_not_efficient(data):
    _, rois, truth, bound = data
    result = fit_arrays(rois[:3000], method="lsq")
    z = ((result.params - truth[:3000]) / bound[:3000])[result.converged]
    assert result.converged.mean() >= 0.995
    assert np.all(np.abs(z[:, :2].mean(axis=0)) < 5 / np.sqrt(len(z)))
    # unweighted least squares cannot beat the bound; with background it is visibly above it
    assert np.all(z.std(axis=0) > 1.0)

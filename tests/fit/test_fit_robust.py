"""The sandwich covariance of the Gaussian fit matches the actual scatter of its parameters,
for Gaussian spots (where it is the Cramér–Rao bound) and for an aberrated pupil PSF from the
independent validation microscope (where the bound understates the scatter of ρ and the widths).

Truth is the Monte Carlo scatter of K fits of noisy copies of one expected image; a standard
deviation from K samples has a relative standard error 1/sqrt(2(K-1)), and the tolerance is 3 of
them plus 5 % for the spread of the per-ROI estimates' mean.
"""

import numpy as np

from latentz.fit import crlb, fit_rois, render_rois
from latentz.fit.robust import misspecified_errors

K = 300
READNOISE = 1.5
TOL = 3 / np.sqrt(2 * (K - 1)) + 0.05
WIDTHS = [4, 5, 6]  # wx, wy, rho columns


def _scatter_and_errors(expected: np.ndarray, seed: int):
    rng = np.random.default_rng(seed)
    rois = rng.poisson(np.broadcast_to(expected, (K, *expected.shape))) + rng.normal(
        0.0, READNOISE, (K, *expected.shape)
    )
    fit = fit_rois(rois, device="cpu")
    params = fit[["x", "y", "amplitude", "background", "wx", "wy", "rho"]].to_numpy()
    good = np.all(np.isfinite(params), axis=1) & fit["converged"].to_numpy()
    params, rois = params[good], rois[good]
    sandwich = misspecified_errors(rois, params, readnoise=READNOISE)
    bound = crlb(params, shape=expected.shape, readnoise=READNOISE)
    return np.std(params, axis=0), np.nanmean(sandwich, axis=0), np.nanmean(bound, axis=0)


def test_sandwich_is_the_bound_for_gaussian_spots():
    truth = {"x": [7.2], "y": [6.9], "amplitude": [80.0], "background": [2.0], "wx": [1.6],
             "wy": [2.1], "rho": [0.2]}  # fmt: skip
    scatter, sandwich, bound = _scatter_and_errors(render_rois(truth, shape=15)[0], seed=1)
    np.testing.assert_allclose(sandwich[WIDTHS], bound[WIDTHS], rtol=0.05)
    np.testing.assert_allclose(scatter[WIDTHS], sandwich[WIDTHS], rtol=TOL)


def test_sandwich_holds_the_scatter_of_a_pupil_psf():
    from latentz.validation import AberrationFields, Microscope
    from latentz.validation.datasets import render_patches

    microscope = Microscope()
    fields = AberrationFields.random((64, 64), seed=3, pixel_size_nm=microscope.pixel_size_nm)
    patch = render_patches(microscope, fields, 32.3, 31.8, np.array([-300.0]), 15)[0]
    expected = 900.0 * patch + 2.0
    scatter, sandwich, bound = _scatter_and_errors(expected, seed=2)
    print("scatter / bound", scatter[WIDTHS] / bound[WIDTHS])
    print("scatter / sandwich", scatter[WIDTHS] / sandwich[WIDTHS])
    np.testing.assert_allclose(scatter[WIDTHS], sandwich[WIDTHS], rtol=TOL)
    assert np.max(scatter[WIDTHS] / bound[WIDTHS]) > 1 + TOL  # the bound alone would fail

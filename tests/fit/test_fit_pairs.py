"""Two-emitter fits (`latentz.fit.pairs`) against the geometry that made the ROIs.

ROIs of eq. 1 with Poisson noise: one emitter (random widths 1–2 px, ρ within ±0.5) or two
round emitters of width σ = 1.3 px, 1–2 FWHM apart (FWHM = 2.355 σ: 3.1–6.1 px) along a random
direction, each of 2,000–5,000 photons over 10 photons/px, in 13 x 13 px ROIs. The truth is
where each emitter was drawn; the start is latentz's one-emitter fit, as in `localize`.
"""

import numpy as np
import pytest

from latentz.fit import fit_arrays, render_rois
from latentz.fit import pairs as fit_pairs_module
from latentz.fit.pairs import fit_pairs, is_split

SIZE, SIGMA, N = 13, 1.3, 200
FWHM = 2 * np.sqrt(2 * np.log(2)) * SIGMA


def emitters(centre, photons, wx, wy, rho):
    """Expected photoelectrons (n, SIZE, SIZE) of one eq. 1 emitter per ROI, no background."""
    table = {"x": centre[:, 0], "y": centre[:, 1], "photons": photons, "wx": wx, "wy": wy,
             "rho": rho, "background": np.zeros(len(centre))}  # fmt: skip
    return render_rois(table, shape=SIZE)


def pair_rois(seed, shift_x=0.0):
    """(truth (N, 2 emitters, x y), Poisson ROIs, photons (N, 2)) of N pairs centred
    ``shift_x`` px right of the ROI's centre, within ±0.5 px."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, np.pi, N)
    half = rng.uniform(1.0, 2.0, N) * FWHM / 2
    centre = (SIZE - 1) / 2 + np.array([shift_x, 0.0]) + rng.uniform(-0.5, 0.5, (N, 2))
    offset = half[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    truth = np.stack([centre + offset, centre - offset], axis=1)
    round_ = np.full(N, SIGMA)
    photons = rng.uniform(2e3, 5e3, (2, N))
    mu = 10.0 + sum(emitters(truth[:, k], photons[k], round_, round_, np.zeros(N)) for k in (0, 1))
    return truth, rng.poisson(mu).astype(float), photons.T


@pytest.fixture(scope="module")
def pairs():
    truth, rois, photons = pair_rois(31)
    one = fit_arrays(rois, device="cpu").params
    return truth, fit_pairs(rois, one), fit_pairs(rois, one, errors="sandwich"), photons


def matched_errors(truth, fit):
    """(n, 2, 2) x, y of each fitted emitter minus those of the true emitter paired with it
    (the pairing with the smaller total distance)."""
    found = fit.params[:, :, :2]
    straight = found - truth
    crossed = found - truth[:, ::-1]
    swap = np.abs(crossed).sum(axis=(1, 2)) < np.abs(straight).sum(axis=(1, 2))
    return np.where(swap[:, None, None], crossed, straight)


def test_pairs_one_to_two_fwhm_apart_are_split_near_their_true_positions(pairs):
    truth, fit, *_ = pairs
    split = is_split(fit, (SIZE, SIZE))
    # Every pair is far above the limit (the smallest likelihood ratio measured here is 155,
    # against 60): 99 % of 200 allows two failures (measured: none).
    assert split.mean() >= 0.99, split.mean()
    z = np.abs(matched_errors(truth, fit)[split]) / fit.errors[split][:, :, :2]
    # near the truth: within 5 Cramér–Rao bounds (a normal error passes 5σ once in 10^6)
    assert np.all(z < 5), z.max()


@pytest.mark.parametrize("errors", ["crlb", "sandwich"])
def test_pair_errors_cover_68_percent(pairs, errors):
    truth, crlb, sandwich, _ = pairs
    fit = crlb if errors == "crlb" else sandwich
    split = is_split(fit, (SIZE, SIZE))
    # each fitted emitter's own bound on x and on y: 4 N values
    inside = np.abs(matched_errors(truth, fit)[split]) <= fit.errors[split][:, :, :2]
    # 68.3 % ± 2 binomial standard errors of ~800 values (1.6 %): 65–72 %, widened to 63–74 %
    # for the pairs' correlation (each pair's x errors share one fit). Measured: 69.6 % with
    # the bound, 65.6 % with the sandwich (its variance is itself estimated from the ROI).
    assert 0.63 <= inside.mean() <= 0.74, inside.mean()


def test_single_emitters_are_not_split():
    rng = np.random.default_rng(32)
    n = 300
    centre = (SIZE - 1) / 2 + rng.uniform(-0.5, 0.5, (n, 2))
    photons = np.exp(rng.uniform(np.log(1e3), np.log(1e4), n))
    mu = 10.0 + emitters(centre, photons, rng.uniform(1.0, 2.0, n), rng.uniform(1.0, 2.0, n),
                         rng.uniform(-0.5, 0.5, n))  # fmt: skip
    rois = rng.poisson(mu).astype(float)
    fit = fit_pairs(rois, fit_arrays(rois, device="cpu").params)
    # One emitter fitted twice gives a likelihood ratio near chi-square(6) (99.9 % point 22):
    # the limit of 60 should split none (measured: none, the largest ratio 22). Bound: at most
    # 3 of 300; were the true rate 1 %, 3 or
    # fewer would still occur with probability 0.65, and at a 3 % rate with probability 0.02.
    assert is_split(fit, (SIZE, SIZE)).sum() <= 3


def test_pairs_in_a_roi_clipped_by_the_frame_are_fitted_on_the_pixels_inside():
    """The frame's edge cuts the ROI's first three columns (NaN there, as `localize` cuts them):
    the pair is fitted on the columns inside, and found where it was drawn."""
    cut = 3
    truth, rois, _ = pair_rois(33, shift_x=1.0)
    rois[:, :, :cut] = np.nan
    windows = np.tile([0, SIZE, cut, SIZE], (N, 1))
    one = fit_arrays(rois, device="cpu", windows=windows).params
    fit = fit_pairs(rois, one)
    split = is_split(fit, (SIZE, SIZE))
    # the emitters lie 1-2 FWHM apart, all inside the frame's columns (x >= 3.4 px), with up to
    # a third of their light cut: 97 % of 200 allows six failures (measured: all)
    assert split.mean() >= 0.97, split.mean()
    errors = matched_errors(truth, fit)[split]
    assert np.all(np.abs(errors) < 5 * fit.errors[split][:, :, :2])  # within 5 Cramér–Rao bounds
    inside = np.abs(errors) <= fit.errors[split][:, :, :2]
    # the bounds grow with the pixels left out and still cover: 68.3 % within 63-74 % as above
    # (measured: 69.6 %)
    assert 0.63 <= inside.mean() <= 0.74, inside.mean()


def test_pair_correlations_match_the_scatter_of_the_fitted_amplitudes_and_widths(pairs):
    """Each emitter's reported correlations of amplitude, wx and wy (from the two-emitter
    covariance) against the correlations of their errors over the split pairs; the truth is what
    the ROIs were drawn with (round width σ, the photons, so amplitude photons / (2π σ²)).
    Measured: reported −0.42, −0.42, 0.12 against observed −0.36, −0.29, 0.13."""
    truth, fit, _, photons = pairs
    split = is_split(fit, (SIZE, SIZE))
    found, drawn = fit.params[split], photons[split]
    swap = np.abs(matched_errors(truth, fit)[split] - (found[:, :, :2] - truth[split])).sum(
        axis=(1, 2)) > 0  # fmt: skip
    drawn = np.where(swap[:, None], drawn[:, ::-1], drawn)
    amplitude = drawn / (2 * np.pi * SIGMA**2)
    errors = np.stack([found[:, :, 2] - amplitude, found[:, :, 4] - SIGMA,
                       found[:, :, 5] - SIGMA], axis=-1).reshape(-1, 3)  # fmt: skip
    reported = fit.correlations[split].reshape(-1, 6)[:, [0, 1, 3]].mean(axis=0)
    observed = np.corrcoef(errors.T)[[0, 0, 1], [1, 2, 2]]  # (A, wx), (A, wy), (wx, wy)
    # ~400 emitters (two per pair, not independent): a correlation's sampling error is about
    # 1/√200 = 0.07; within 2 of it
    assert np.all(np.abs(observed - reported) <= 0.14), (observed, reported)


def test_the_kernel_fits_pairs_as_its_numpy_twin_does(monkeypatch):
    """`fit_pairs` through the numba kernel and through its NumPy twin
    (`_levenberg_marquardt`), on 200 pairs and 200 single emitters, every seventh ROI clipped
    by the frame, with read noise: the two differ by rounding only, so they keep the same fits
    and splits. Measured on seeds 40, 42, 44, 46: every row stops after the same iterations,
    converged fits within 2e-9 bounds of each other, errors within 1e-8 (relative)."""
    truth, pairs, _ = pair_rois(40)
    rng = np.random.default_rng(41)
    centre = (SIZE - 1) / 2 + rng.uniform(-0.5, 0.5, (N, 2))
    single = 10.0 + emitters(centre, rng.uniform(2e3, 5e3, N), rng.uniform(1.0, 2.0, N),
                             rng.uniform(1.0, 2.0, N), rng.uniform(-0.5, 0.5, N))  # fmt: skip
    rois = np.concatenate([pairs, rng.poisson(single).astype(float)])
    rois[::7, :, :3] = np.nan
    windows = np.tile([0, SIZE, 0, SIZE], (len(rois), 1))
    windows[::7, 2] = 3
    one = fit_arrays(rois, device="cpu", readnoise=1.5, windows=windows).params
    got = fit_pairs(rois, one, readnoise=1.5, errors="sandwich")
    monkeypatch.setattr(fit_pairs_module, "_fit_starts", fit_pairs_module._levenberg_marquardt)
    want = fit_pairs(rois, one, readnoise=1.5, errors="sandwich")
    np.testing.assert_array_equal(got.converged, want.converged)
    np.testing.assert_array_equal(is_split(got, (SIZE, SIZE)), is_split(want, (SIZE, SIZE)))
    assert got.converged.sum() >= 280  # pairs, and single emitters whose second one converged
    # a fit stops within tol = 0.1 bounds of its optimum: rounding may end one an iteration
    # earlier (within 0.1 bounds), else it moves the fit by far less than a bound
    same = got.converged & (got.iterations == want.iterations)
    assert same.sum() >= 0.99 * got.converged.sum()
    z = np.abs(got.params - want.params) / want.errors
    assert np.all(z[got.converged] <= 0.1) and np.all(z[same] <= 1e-6), z[got.converged].max()
    np.testing.assert_allclose(got.errors[same], want.errors[same], rtol=1e-6)
    np.testing.assert_allclose(got.loglik[same], want.loglik[same], rtol=1e-12)

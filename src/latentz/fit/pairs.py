"""Two-emitter fits of ROIs that may hold a close pair, and the test that keeps the second one.

Where one Gaussian of eq. 1 fits a ROI poorly, :func:`fit_pairs` fits the sum of two, each with
its own position, amplitude, widths and ρ, over one shared background (13 parameters), by
Poisson maximum likelihood (Levenberg–Marquardt on the Fisher scoring matrix, read noise by
``d + s^2 ~ Poisson(mu + s^2)`` as in :mod:`latentz.fit.api`), in the numba kernel
:func:`latentz.fit._pair_kernels.pair_fits`, whose NumPy twin, vectorised over ROIs, is
:func:`_levenberg_marquardt`. It starts twice: the one-emitter fit split along its long axis, and
two round emitters at the ROI's two brightest peaks; the start that ends with the higher
likelihood wins.

:func:`is_split` keeps the second emitter, as the multi-emitter fitting of ThunderSTORM and SMAP
does, when it raises the likelihood significantly: the likelihood ratio ``2 (l_2 - l_1)``, over
the dispersion of one emitter's fit, above :data:`LR_LIMIT`, with each emitter holding at least
:data:`MIN_SHARE` of the pair's photons, the two at least :data:`MIN_SEPARATION_PX` apart and
both inside the ROI. Errors are the Cramér–Rao bounds of the 13-parameter model, or its sandwich
covariance.

A real PSF is not the Gaussian of eq. 1, and a second Gaussian always takes up part of the
difference: on simulated pupil-function PSFs the ratio of isolated emitters reaches several
hundred, and on a bright defocused bead (30,000 photons) 130–500. That misfit grows with the
photons, as the pixels' variance about eq. 1 does: the dispersion (the Pearson chi-square over
its degrees of freedom) that one emitter's fit shows. As in a quasi-likelihood test of nested
models, the likelihood ratio is divided by it (1 where the spots are eq. 1).
:mod:`latentz.localization.pairs` measures it on the isolated fits where neither a calibration
nor the spot's width shows more than one emitter, fits pairs only where one emitter's shape is
beyond what one emitter looks like, and keeps them only where both emitters look like one.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from scipy.special import gammaln

from latentz._shared.threads import SMALL_BATCH, one_thread_if
from latentz._shared.validate import check_choice
from latentz.fit._model import N_PARAMS, model_and_jacobian, photons_of
from latentz.fit._pair_kernels import pair_fits
from latentz.fit.api import CORRELATED, correlations_of

__all__ = ["PairFit", "fit_pairs", "is_split", "LR_LIMIT", "MIN_SHARE", "MIN_SEPARATION_PX"]

#: Likelihood ratio 2 (l_2 - l_1) above which the second emitter is significant: one Gaussian
#: emitter fitted twice gives about chi-square(6), whose 99.9 % point is 22; 60 leaves room for
#: the second emitter's position, undefined where its amplitude is zero.
LR_LIMIT = 60.0
#: Least share of the pair's photons each emitter of a kept pair holds.
MIN_SHARE = 0.1
#: Least distance (pixels) between the emitters of a kept pair: closer fits are one emitter
#: (`latentz.localization.quality.DUPLICATE_PX`).
MIN_SEPARATION_PX = 1.0
_N = 2 * 6 + 1  # per emitter x, y, A, log wx, log wy, atanh rho; then the shared background
_W_MIN, _RHO_MAX = 0.3, 0.95
_BATCH = 128  # ROIs fitted at once: bounds the memory of `_natural`'s Jacobians (128 x p x 13)


class PairFit(NamedTuple):
    """Arrays returned by `fit_pairs`, one row per ROI.

    Attributes
    ----------
    params : ndarray (n, 2, 7)
        Each emitter's natural parameters (`latentz.fit.PARAMS`: x, y in ROI pixels, amplitude,
        the shared background, wx, wy in pixels, ρ).
    errors : ndarray (n, 2, 7)
        Their standard deviations in the two-emitter model (`fit_pairs`' ``errors``); NaN where
        its information is singular.
    correlations : ndarray (n, 2, 6)
        Each emitter's correlations of the pairs `latentz.fit.api.CORRELATED` (amplitude, wx,
        wy, ρ) in the same covariance, as `latentz.fit.FitResult.correlations` holds them.
    loglik : ndarray (n,)
        Log-likelihood of the two-emitter fit, as `latentz.fit.FitResult.loglik`.
    chi2 : ndarray (n,)
        Pearson chi-square of the two-emitter fit, ``sum (d - mu)^2 / (mu + s^2)``.
    iterations : ndarray (n,) of int
        Levenberg–Marquardt iterations of the start that won.
    ratio : ndarray (n,)
        ``2 (loglik - loglik of the one-emitter fit)``: the likelihood-ratio statistic.
    converged : ndarray (n,) of bool
        The fit stopped within ``tol`` Cramér–Rao bounds of its optimum, off the width and ρ
        bounds, with an invertible information.
    """

    params: np.ndarray
    errors: np.ndarray
    correlations: np.ndarray
    loglik: np.ndarray
    chi2: np.ndarray
    iterations: np.ndarray
    ratio: np.ndarray
    converged: np.ndarray


def _model(theta: np.ndarray, grid: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, ...]:
    """Expected counts (n, p) of two Gaussians over a background and their derivatives
    (n, p, 13) with respect to the internal parameters ``theta`` (n, 13)."""
    xp, yp = grid
    jac = np.empty((len(theta), xp.size, _N))
    mu = np.repeat(theta[:, 12, None], xp.size, axis=1)
    for k in (0, 6):
        x, y, amp, lwx, lwy, trho = (theta[:, k + i, None] for i in range(6))
        wx, wy, rho = np.exp(lwx), np.exp(lwy), np.tanh(trho)
        om = 1.0 - rho**2
        u, v = (xp - x) / wx, (yp - y) / wy
        a, b = (u - rho * v) / om, (v - rho * u) / om
        q = u * a + v * b
        g = np.exp(-0.5 * q)
        ag = amp * g
        mu += ag
        for i, column in enumerate((ag * a / wx, ag * b / wy, g, ag * u * a, ag * v * b,
                                    ag * (u * v - rho * q))):  # fmt: skip
            jac[..., k + i] = column
    jac[..., 12] = 1.0
    return mu, jac


def _loglik(data: np.ndarray, mu: np.ndarray, s2: float, seen: np.ndarray) -> np.ndarray:
    """Σ d' log mu' − mu' with d' = d + s², mu' = mu + s² (the Poisson log-likelihood less its
    data-only constant) over the ``seen`` pixels (1, else 0), per ROI."""
    m = np.maximum(mu + s2, 1e-12)
    return np.sum(seen * ((data + s2) * np.log(m) - m), axis=1)


def _bounds(shape: tuple[int, int], s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Box of the internal parameters, as `latentz.fit.api.parameter_bounds` per emitter."""
    h, w = shape
    big = math.log(max(h, w))
    one_lo = [-1.0, -1.0, 0.0, math.log(_W_MIN), math.log(_W_MIN), -math.atanh(_RHO_MAX)]
    one_hi = [w, h, np.inf, big, big, math.atanh(_RHO_MAX)]
    return np.array(one_lo * 2 + [-s2 + 1e-3]), np.array(one_hi * 2 + [np.inf])


def _internal(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Internal parameters (n, 13) of two emitters given as natural parameters (n, 7)."""
    parts = []
    for p in (first, second):
        parts += [p[:, 0], p[:, 1], p[:, 2], np.log(p[:, 4]), np.log(p[:, 5]),
                  np.arctanh(np.clip(p[:, 6], -_RHO_MAX, _RHO_MAX))]  # fmt: skip
    return np.stack([*parts, first[:, 3]], axis=1)


def _two_peaks(rois: np.ndarray, one: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices (n,) of the two brightest local maxima of each ROI after a 3 x 3 box
    filter, the second being the brightest pixel of the one-emitter fit's residual where the
    ROI has one maximum only."""
    n, h, w = rois.shape
    padded = np.pad(rois, ((0, 0), (1, 1), (1, 1)), mode="edge")
    box = sum(padded[:, i : i + h, j : j + w] for i in range(3) for j in range(3))
    wide = np.pad(box, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    neighbours = np.max([wide[:, i : i + h, j : j + w] for i in range(3) for j in range(3)
                         if (i, j) != (1, 1)], axis=0)  # fmt: skip
    score = np.where(box >= neighbours, box, -np.inf).reshape(n, -1)
    order = np.argsort(-score, axis=1)
    first, second = order[:, 0], order[:, 1]
    mu, _ = model_and_jacobian(one, (h, w), jacobian=False)
    residual_peak = (rois.reshape(n, -1) - mu).argmax(axis=1)
    lone = ~np.isfinite(score[np.arange(n), second])
    return first, np.where(lone, residual_peak, second)


def _starts(rois: np.ndarray, one: np.ndarray, s2: float) -> np.ndarray:
    """Two starts per ROI (2n, 13) from the one-emitter fit ``one`` (n, 7, natural): split
    along its long axis, and two round emitters at the ROI's two brightest peaks."""
    n, h, w = rois.shape
    one = one.copy()
    one[:, 4:6] = np.clip(one[:, 4:6], 0.5, 0.5 * max(h, w))
    wx, wy, rho = one[:, 4], one[:, 5], np.clip(one[:, 6], -0.9, 0.9)
    cov = np.stack([wx**2, rho * wx * wy, rho * wx * wy, wy**2], 1).reshape(n, 2, 2)
    var, vec = np.linalg.eigh(cov)  # ascending: the long axis last
    half = np.sqrt(np.maximum(var[:, 1] - var[:, 0], 0.25))  # the pair's offset, at least 0.5 px
    each = one.copy()
    each[:, 4] = each[:, 5] = np.clip(np.sqrt(var[:, 0]), 0.7, 3.0)
    each[:, 6] = 0.0
    each[:, 2] = 0.5 * photons_of(one[:, 2], wx, wy, rho) / (2 * np.pi * each[:, 4] ** 2)
    shift = half[:, None] * vec[:, :, 1]
    a, b = each.copy(), each.copy()
    a[:, :2] += shift
    b[:, :2] -= shift
    peaks = []
    for index in _two_peaks(rois, one):
        start = each.copy()
        start[:, 1], start[:, 0] = np.divmod(index, w)
        height = rois.reshape(n, -1)[np.arange(n), index] - one[:, 3]
        start[:, 2] = np.maximum(height, 1.0)
        peaks.append(start)
    lo, hi = _bounds((h, w), s2)
    return np.clip(np.concatenate([_internal(a, b), _internal(*peaks)]), lo, hi)


def _levenberg_marquardt(
    data: np.ndarray, seen: np.ndarray, theta: np.ndarray, shape: tuple[int, int], s2: float,
    max_iter: int, tol: float,
) -> tuple[np.ndarray, ...]:  # fmt: skip
    """Maximise the Poisson likelihood over the ``seen`` pixels from ``theta`` (n, 13) for every
    ROI of ``data`` (n, p); returns (theta, loglik, stopped within tol, iterations). The NumPy
    twin of `_fit_starts`, for the tests."""
    grid = tuple(g.ravel().astype(float) for g in np.indices(shape)[::-1])
    lo, hi = _bounds(shape, s2)
    loglik = _loglik(data, _model(theta, grid)[0], s2, seen)
    damping = np.full(len(theta), 1e-3)
    done, converged = np.zeros(len(theta), bool), np.zeros(len(theta), bool)
    iterations = np.zeros(len(theta), np.int64)
    for _ in range(max_iter):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        iterations[act] += 1
        mu, jac = _model(theta[act], grid)
        m = np.maximum(mu + s2, 1e-12)
        grad = np.matmul((seen[act] * ((data[act] + s2) / m - 1.0))[:, None, :], jac)[:, 0]
        info = np.matmul((jac * (seen[act] / m)[:, :, None]).transpose(0, 2, 1), jac)
        diag = np.diagonal(info, 0, 1, 2)
        system = info + (damping[act, None] * diag + 1e-9 * (diag + 1.0))[:, :, None] * np.eye(_N)
        step = np.linalg.solve(system, grad[:, :, None])[:, :, 0]
        trial = np.clip(theta[act] + step, lo, hi)
        new = _loglik(data[act], _model(trial, grid)[0], s2, seen[act])
        better = new > loglik[act]
        with np.errstate(invalid="ignore", divide="ignore"):  # 1/I_kk: at most the bound
            small = np.all(step**2 * diag <= tol**2, axis=1)
        theta[act[better]] = trial[better]
        loglik[act[better]] = new[better]
        damping[act] = np.where(better, damping[act] / 10, damping[act] * 10)
        near = small
        converged[act] = near
        done[act] = near | (damping[act] > 1e8)
    return theta, loglik, converged, iterations


def _fit_starts(
    data: np.ndarray, seen: np.ndarray, theta: np.ndarray, shape: tuple[int, int], s2: float,
    max_iter: int, tol: float,
) -> tuple[np.ndarray, ...]:  # fmt: skip
    """`_levenberg_marquardt` in the numba kernel `latentz.fit._pair_kernels.pair_fits`; fewer
    than `SMALL_BATCH` rows on one thread."""
    n = len(theta)
    lo, hi = _bounds(shape, s2)
    theta = np.ascontiguousarray(theta, dtype=np.float64)
    loglik, converged = np.empty(n), np.empty(n, dtype=np.bool_)
    iterations = np.empty(n, dtype=np.int64)
    with one_thread_if(n < SMALL_BATCH), numba.parallel_chunksize(1):
        pair_fits(
            np.ascontiguousarray(data), np.ascontiguousarray(seen), theta, lo, hi, *shape, s2,
            max_iter, tol, min(n, 64 * numba.get_num_threads()), loglik, converged, iterations,
        )  # fmt: skip
    return theta, loglik, converged, iterations


def _natural(
    theta: np.ndarray,
    data: np.ndarray,
    seen: np.ndarray,
    shape: tuple[int, int],
    s2: float,
    sandwich: bool,
) -> tuple[np.ndarray, ...]:
    """Natural parameters (n, 2, 7), their standard deviations (n, 2, 7), each emitter's
    correlations (n, 2, 6; of internal parameters, which each map to one natural parameter by an
    increasing function, so to first order the same) and whether the information was invertible
    (n,), at internal parameters ``theta`` (n, 13) fitted to the
    ``seen`` pixels of ``data`` (n, p): the Cramér–Rao bounds, or with ``sandwich`` the
    covariance of a misspecified fit, ``I⁻¹ (Σ J Jᵀ (d − mu)² / (mu + s²)²) I⁻¹`` times
    ``p / (p − 13)`` (p seen pixels) for the residuals' lost degrees of freedom (the bound on
    average where the model is right)."""
    grid = tuple(g.ravel().astype(float) for g in np.indices(shape)[::-1])
    mu, jac = _model(theta, grid)
    m = np.maximum(mu + s2, 1e-12)
    info = np.matmul((jac * (seen / m)[:, :, None]).transpose(0, 2, 1), jac)
    usable = np.isfinite(info).all(axis=(1, 2))
    usable[usable] = np.linalg.cond(info[usable]) < 1e12
    cov = np.full((len(theta), _N, _N), np.nan)
    cov[usable] = np.linalg.inv(info[usable])
    if sandwich:
        scaled = jac * (seen * (data - mu) / m)[:, :, None]
        # residuals of a fit are smaller than the noise by the parameters they took up: p/(p−13)
        p = seen.sum(axis=1)[:, None, None]
        meat = np.matmul(scaled.transpose(0, 2, 1), scaled) * (p / np.maximum(p - _N, 1.0))
        cov[usable] = cov[usable] @ meat[usable] @ cov[usable]
    sd = np.sqrt(np.maximum(np.diagonal(cov, 0, 1, 2), 0.0))
    params, errors = np.empty((len(theta), 2, N_PARAMS)), np.empty((len(theta), 2, N_PARAMS))
    correlations = np.empty((len(theta), 2, len(CORRELATED)))
    for e, k in enumerate((0, 6)):
        own = [k, k + 1, k + 2, 12, k + 3, k + 4, k + 5]  # in the order of PARAMS
        correlations[:, e] = correlations_of(cov[:, own][:, :, own])
        wx, wy, rho = np.exp(theta[:, k + 3]), np.exp(theta[:, k + 4]), np.tanh(theta[:, k + 5])
        params[:, e] = np.stack([theta[:, k], theta[:, k + 1], theta[:, k + 2], theta[:, 12],
                                 wx, wy, rho], 1)  # fmt: skip
        errors[:, e] = np.stack([sd[:, k], sd[:, k + 1], sd[:, k + 2], sd[:, 12],
                                 wx * sd[:, k + 3], wy * sd[:, k + 4],
                                 (1 - rho**2) * sd[:, k + 5]], 1)  # fmt: skip
    return params, errors, correlations, usable


def fit_pairs(
    rois: np.ndarray,
    one: np.ndarray,
    *,
    readnoise: float = 0.0,
    max_iter: int = 50,
    tol: float = 0.1,
    errors: str = "crlb",
) -> PairFit:
    """Fit two Gaussians of eq. 1 over one background to each ROI, starting from its
    one-emitter fit.

    Parameters
    ----------
    rois : ndarray (n, h, w)
        Photoelectrons per pixel; NaN pixels (a ROI clipped to the frame: those outside it) are
        left out of the likelihood, as :mod:`latentz.fit.windows` leaves them out.
    one : ndarray (n, 7)
        The one-emitter fits in natural parameters (`latentz.fit.PARAMS`), as
        `latentz.fit.fit_arrays` returns them.
    readnoise : float
        Read-noise standard deviation in photoelectrons.
    max_iter, tol : int, float
        Iterations per start, and the stop within ``tol`` Cramér–Rao bounds of the optimum.
    errors : {"crlb", "sandwich"}
        ``"crlb"``: the Cramér–Rao bounds of the two-emitter model, exact for Gaussian spots.
        ``"sandwich"``: the covariance of a misspecified fit, which holds the scatter where a
        real PSF is fitted with Gaussians (as `latentz.fit.fit_arrays` ``errors="sandwich"``).

    Returns
    -------
    PairFit
    """
    rois, one = np.asarray(rois, dtype=np.float64), np.asarray(one, dtype=np.float64)
    sandwich = check_choice("errors", errors, ("crlb", "sandwich")) == "sandwich"
    s2 = float(readnoise) ** 2
    parts = [
        _fit_batch(rois[k : k + _BATCH], one[k : k + _BATCH], s2, max_iter, tol, sandwich)
        for k in range(0, len(rois), _BATCH)
    ]
    if not parts:
        shapes = ((2, N_PARAMS), (2, N_PARAMS), (2, len(CORRELATED)), (), (), (), (), ())
        return PairFit(*(np.zeros((0, *shape)) for shape in shapes))
    return PairFit(*(np.concatenate(field) for field in zip(*parts, strict=True)))


def _fit_batch(
    rois: np.ndarray, one: np.ndarray, s2: float, max_iter: int, tol: float, sandwich: bool
) -> PairFit:
    """`fit_pairs` of one batch of ROIs (n, h, w) with read-noise variance ``s2``."""
    n, h, w = rois.shape
    seen = np.isfinite(rois)
    rois = np.where(seen, rois, 0.0)
    data, seen = rois.reshape(n, -1), seen.reshape(n, -1).astype(float)
    theta, loglik, stopped, iterations = _fit_starts(
        np.concatenate([data, data]), np.concatenate([seen, seen]), _starts(rois, one, s2),
        (h, w), s2, max_iter, tol,
    )  # fmt: skip
    best = np.where(loglik[n:] > loglik[:n], np.arange(n) + n, np.arange(n))
    best = np.where(np.isfinite(loglik[best]), best, np.arange(n))
    theta, loglik, stopped = theta[best], loglik[best], stopped[best]
    params, errors, correlations, usable = _natural(theta, data, seen, (h, w), s2, sandwich)
    lo, hi = _bounds((h, w), s2)
    shape = [3, 4, 5, 9, 10, 11]  # log widths and atanh rho of both emitters
    inside = np.all((theta[:, shape] > lo[shape] + 1e-6) & (theta[:, shape] < hi[shape] - 1e-6), 1)
    grid = tuple(g.ravel().astype(float) for g in np.indices((h, w))[::-1])
    mu = _model(theta, grid)[0]
    single = _loglik(data, model_and_jacobian(one, (h, w), jacobian=False)[0], s2, seen)
    constant = np.sum(seen * gammaln(np.maximum(data + s2, 0.0) + 1.0), axis=1)
    chi2 = np.sum(seen * (data - mu) ** 2 / np.maximum(mu + s2, 1e-12), 1)
    return PairFit(
        params, errors, correlations, loglik - constant, chi2,
        iterations[best], 2.0 * (loglik - single), stopped & usable & inside,
    )  # fmt: skip


def is_split(
    fit: PairFit, shape: tuple[int, int], dispersion: np.ndarray | float = 1.0
) -> np.ndarray:
    """Which ROIs (of ``shape``, pixels) hold two emitters: the two-emitter fit converged, its
    likelihood ratio over ``dispersion`` exceeds :data:`LR_LIMIT`, each emitter holds at least
    :data:`MIN_SHARE` of the photons, they lie :data:`MIN_SEPARATION_PX` apart or more, and both
    inside the ROI. ``dispersion`` (per ROI, or one number) is the Pearson chi-square over its
    degrees of freedom that one emitter of the one-emitter fit's brightness and shape shows: the
    pixels' variance about eq. 1 in units of the noise's (1: the spots are eq. 1)."""
    h, w = shape
    p = fit.params
    photons = photons_of(p[..., 2], p[..., 4], p[..., 5], p[..., 6])
    with np.errstate(invalid="ignore", divide="ignore"):
        share = photons.min(axis=1) / photons.sum(axis=1)
    inside = np.all((p[..., 0] >= -0.5) & (p[..., 0] <= w - 0.5) & (p[..., 1] >= -0.5)
                    & (p[..., 1] <= h - 0.5), axis=1)  # fmt: skip
    apart = np.hypot(*(p[:, 0, :2] - p[:, 1, :2]).T) >= MIN_SEPARATION_PX
    with np.errstate(invalid="ignore"):
        significant = fit.ratio / dispersion > LR_LIMIT
        return fit.converged & significant & (share >= MIN_SHARE) & apart & inside

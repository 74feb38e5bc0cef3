"""Errors of the Gaussian fit when the PSF is not a Gaussian (model misspecification).

The Cramér–Rao bound of eq. 1 (:func:`~latentz.fit.crlb`) is the covariance of the maximum-
likelihood fit only when the data are Gaussian spots. A real PSF is not: then the fit converges
to the Gaussian nearest the PSF, and its covariance is the sandwich ``A⁻¹ I A⁻¹``, where ``I`` is
the Fisher information (the variance of the score under Poisson + read noise) and ``A`` the
*observed* information, the negative Hessian of the log-likelihood at the fit, computed from the
ROI's own pixels. For a Gaussian spot A → I and the sandwich is the bound; for a PSF whose wings
or rings the Gaussian misses, A < I and the widths scatter more than the bound says (by up to
1.6x for ρ and the widths near focus at 10³ photons on the validation microscope;
``docs/accuracy.md``).

:func:`sandwich_batch` computes it in the fit's own numba code (one evaluation of the score and
Fisher matrix of :func:`latentz.fit._kernels._evaluate` at the fit, and one of the score alone
per parameter, a forward difference), about the cost of a few iterations of the fit;
:func:`fit_arrays <latentz.fit.fit_arrays>` reports its diagonal as the ``*_err`` columns.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from latentz._shared.threads import SMALL_BATCH, one_thread_if
from latentz.fit._kernels import MLE, _cholesky, _evaluate, _solve, to_internal
from latentz.fit._model import N_PARAMS, as_param_array

__all__ = ["misspecified_covariance", "misspecified_errors", "sandwich_batch"]

#: Forward-difference step of the score, relative to max(|internal parameter|, 1).
_STEP = 1e-6


@numba.njit(cache=True)
def _sandwich_one(roi, natural, s2, scratch, vecs, mats, out):
    """Sandwich covariance (7, 7) of one ROI's MLE fit ``natural`` into ``out``; False (and
    ``out`` untouched) where the observed or Fisher information is not positive definite."""
    h, w = roi.shape
    p, p_try, score, score_try, col = vecs[0], vecs[1], vecs[2], vecs[3], vecs[4]
    info, observed, lower, half = mats[0], mats[1], mats[2], mats[3]
    scale = vecs[5]
    to_internal(natural, p, scale)
    # the model is its own reference (mu_ref = mu_out): only the score and information are used
    _evaluate(roi, p, MLE, s2, 1.0, scratch[0], scratch[1], scratch[0], scratch[1], info, score)
    for k in range(N_PARAMS):
        for m in range(N_PARAMS):
            p_try[m] = p[m]
        step = _STEP * max(abs(p[k]), 1.0)
        p_try[k] = p[k] + step
        _evaluate(roi, p_try, MLE, s2, 1.0, scratch[0], scratch[1], scratch[0], scratch[1],
                  lower, score_try, True, False)  # the score alone: no Fisher matrix
        for m in range(N_PARAMS):
            observed[m, k] = -(score_try[m] - score[m]) / step
    for k in range(N_PARAMS):
        for m in range(k + 1, N_PARAMS):
            observed[k, m] = observed[m, k] = 0.5 * (observed[k, m] + observed[m, k])
    if not _cholesky(info, lower) or not _cholesky(observed, lower):
        return False
    for k in range(N_PARAMS):  # half = A⁻¹ I (A and I symmetric)
        for m in range(N_PARAMS):
            score[m] = info[m, k]
        _solve(lower, score, col)
        for m in range(N_PARAMS):
            half[k, m] = col[m]  # row k of (A⁻¹ I)ᵀ = I A⁻¹
    for k in range(N_PARAMS):  # out = A⁻¹ (I A⁻¹)
        for m in range(N_PARAMS):
            score[m] = half[m, k]
        _solve(lower, score, col)
        for m in range(N_PARAMS):
            out[m, k] = col[m]
    # internal (log w, atanh ρ) → natural (w, ρ): multiply by d natural / d internal
    for k in range(N_PARAMS):
        for m in range(N_PARAMS):
            out[k, m] *= scale[k] * scale[m]
    return True


@numba.njit(parallel=True, nogil=True, cache=True)
def _sandwich_batch(rois, params, s2, n_chunks, out):
    n, h, w = rois.shape
    for c in numba.prange(n_chunks):
        scratch = np.empty((2, h * w))
        vecs = np.empty((6, N_PARAMS))
        mats = np.empty((4, N_PARAMS, N_PARAMS))
        for k in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            usable = params[k, 4] > 0.0 and params[k, 5] > 0.0 and abs(params[k, 6]) < 1.0
            for m in range(N_PARAMS):
                usable = usable and math.isfinite(params[k, m])
            for i in range(h):
                for j in range(w):
                    usable = usable and math.isfinite(rois[k, i, j])
            if not (usable and _sandwich_one(rois[k], params[k], s2, scratch, vecs, mats, out[k])):
                for i in range(N_PARAMS):
                    for j in range(N_PARAMS):
                        out[k, i, j] = np.nan


def sandwich_batch(rois: np.ndarray, params: np.ndarray, readnoise: float) -> np.ndarray:
    """(n, 7, 7) sandwich covariance ``A⁻¹ I A⁻¹`` of the Poisson maximum-likelihood fits
    ``params`` (n, 7, natural, ROI pixels) of ``rois`` (n, h, w, photoelectrons), read noise in
    electrons (module notes). NaN where a parameter or pixel is not finite or either matrix is not
    positive definite (an observed information that is not, at a fit that did not converge).
    Fewer than `SMALL_BATCH` ROIs run on one thread: waking the others costs more."""
    rois = np.ascontiguousarray(rois, dtype=np.float64)
    params = np.ascontiguousarray(params, dtype=np.float64)
    out = np.empty((len(params), N_PARAMS, N_PARAMS))
    if len(params):
        with one_thread_if(len(params) < SMALL_BATCH):
            chunks = min(len(params), 64 * numba.get_num_threads())
            _sandwich_batch(rois, params, float(readnoise) ** 2, chunks, out)
    return out


def misspecified_errors(rois: Any, params: Any, *, readnoise: float = 0.0) -> np.ndarray:
    """(n, 7) standard deviations of the fitted x, y, amplitude, background, wx, wy, ρ: the
    diagonal of :func:`misspecified_covariance` (NaN where it is not positive)."""
    variance = np.diagonal(misspecified_covariance(rois, params, readnoise=readnoise), 0, 1, 2)
    with np.errstate(invalid="ignore"):
        return np.where(variance > 0, np.sqrt(np.abs(variance)), np.nan)


def misspecified_covariance(rois: Any, params: Any, *, readnoise: float = 0.0) -> np.ndarray:
    """(n, 7, 7) sandwich covariance ``A⁻¹ I A⁻¹`` of the fitted x, y, amplitude, background, wx,
    wy, ρ (module notes).

    ``rois`` (n, h, w) in photoelectrons, ``params`` (n, 7) the fit of each in
    :data:`~latentz.fit.PARAMS` order (ROI pixels), ``readnoise`` in electrons. NaN where either
    matrix is not positive definite.
    """
    rois = np.asarray(rois, dtype=np.float64)
    params = as_param_array(params)
    if rois.ndim != 3 or len(rois) != len(params):
        raise ValueError(f"Expected `rois` (n, h, w) with n = {len(params)} rows of `params`, "
                         f"got shape {rois.shape}.")  # fmt: skip
    return sandwich_batch(rois, params, readnoise)

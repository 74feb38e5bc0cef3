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
"""

from __future__ import annotations

from typing import Any

import numpy as np

from latentz.fit._model import N_PARAMS, as_param_array, fisher_information, model_and_jacobian

__all__ = ["misspecified_covariance", "misspecified_errors"]


def _score(rois: np.ndarray, params: np.ndarray, readnoise: float) -> np.ndarray:
    """(n, 7) gradient of the Poisson log-likelihood in the natural parameters."""
    mu, jac = model_and_jacobian(params, rois.shape[1:])
    scale = np.stack([np.ones(len(params))] * 4
                     + [params[:, 4], params[:, 5], 1.0 - params[:, 6] ** 2], axis=1)  # fmt: skip
    shifted = readnoise**2
    weight = (rois.reshape(len(rois), -1) + shifted) / (mu + shifted) - 1.0
    return np.einsum("np,npk->nk", weight, jac / scale[:, None, :])


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
    :data:`~latentz.fit.PARAMS` order (ROI pixels), ``readnoise`` in electrons. The observed
    information is the central difference of the score. NaN where either matrix is singular.
    """
    rois = np.asarray(rois, dtype=np.float64)
    params = as_param_array(params)
    if rois.ndim != 3 or len(rois) != len(params):
        raise ValueError(f"Expected `rois` (n, h, w) with n = {len(params)} rows of `params`, "
                         f"got shape {rois.shape}.")  # fmt: skip
    out = np.full((len(params), N_PARAMS, N_PARAMS), np.nan)
    ok = np.all(np.isfinite(params), axis=1) & np.all(np.isfinite(rois), axis=(1, 2))
    if not ok.any():
        return out
    p, data = params[ok], rois[ok]
    observed = np.zeros((len(p), N_PARAMS, N_PARAMS))
    for k in range(N_PARAMS):
        step = 1e-5 * np.maximum(np.abs(p[:, k]), 1e-2)
        hi, lo = p.copy(), p.copy()
        hi[:, k] += step
        lo[:, k] -= step
        observed[:, :, k] = -(_score(data, hi, readnoise) - _score(data, lo, readnoise)) / (
            2 * step[:, None]
        )
    observed = 0.5 * (observed + observed.transpose(0, 2, 1))
    info = fisher_information(p, shape=data.shape[1:], readnoise=readnoise)
    good = (np.linalg.cond(observed) < 1e12) & (np.linalg.cond(info) < 1e12)
    inverse = np.full_like(observed, np.nan)
    inverse[good] = np.linalg.inv(observed[good])
    out[ok] = np.einsum("nij,njk,nkl->nil", inverse, info, inverse)
    return out

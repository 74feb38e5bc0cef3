"""Plain-NumPy reference twin of :func:`latentz.fit._kernels.fit_batch`.

The same estimators, start, damping schedule, bounds and convergence rule, written with array
operations over the pixels of one ROI and a Python loop over ROIs. It exists so that the tests can
check the compiled kernel against an independent, readable implementation; it is far too slow for
real data.
"""

from __future__ import annotations

import math

import numpy as np

from latentz.fit._kernels import LSQ, MLE, WLSQ
from latentz.fit._model import model_and_jacobian, moment_start

_LAM0 = 1e-3
_LAM_MAX = 1e10


def _natural(p: np.ndarray) -> np.ndarray:
    return np.array([p[0], p[1], p[2], p[3], math.exp(p[4]), math.exp(p[5]), math.tanh(p[6])])


def _internal(theta: np.ndarray) -> np.ndarray:
    return np.array([*theta[:4], math.log(theta[4]), math.log(theta[5]), math.atanh(theta[6])])


def _objective(d, p, shape, method, s2, scale, mu_ref):
    """(objective with reference weights, objective with own weights, H, g, mu) at ``p``."""
    mu, jac = model_and_jacobian(_natural(p)[None], shape)
    mu, jac = mu[0], jac[0]
    if method == MLE:
        mus = mu + s2
        if np.any(mus <= 0):
            return np.inf, np.inf, None, None, mu
        ds = d + s2
        wt = 1.0 / mus
        pos = ds > 0
        ratio = np.where(pos, mus / np.where(pos, ds, 1.0), 1.0)
        terms = np.where(pos, 2.0 * (mus - ds - ds * np.log(ratio)), 2.0 * mus)
        res = np.where(pos, ds * wt - 1.0, -1.0)
        obj_ref = obj_new = terms.sum()
    elif method == WLSQ:
        r = d - mu
        wt = 1.0 / (mu + s2)
        ref = mu if mu_ref is None else mu_ref
        obj_ref = np.sum(r * r / (ref + s2))
        obj_new = np.sum(r * r * wt)
        res = r * wt
    else:
        r = d - mu
        wt = np.full_like(mu, scale)
        obj_ref = obj_new = np.sum(r * r) * scale
        res = r * scale
    hess = jac.T @ (wt[:, None] * jac)
    grad = jac.T @ res
    return obj_ref, obj_new, hess, grad, mu


def fit_reference(rois, *, method, s2, lower, upper, max_iter=50, tol=1e-2, init=None):
    """Fit each ROI; return (params, errors, loglik, chi2, iterations, converged) as the kernel."""
    n, h, w = rois.shape
    shape = (h, w)
    starts = moment_start(rois) if init is None else np.asarray(init, dtype=float)
    out = (np.full((n, 7), np.nan), np.full((n, 7), np.nan), np.full(n, np.nan),
           np.full(n, np.nan), np.zeros(n, dtype=int), np.zeros(n, dtype=bool))  # fmt: skip
    for k in range(n):
        d = rois[k].ravel().astype(float)
        if not np.all(np.isfinite(d)):
            continue
        p = np.clip(_internal(starts[k]), lower, upper)
        scale = 1.0 / max(np.mean(d + s2), 1.0) if method == LSQ else 0.0
        _, obj, hess, grad, mu_ref = _objective(d, p, shape, method, s2, scale, None)
        converged, lam, iters = False, _LAM0, 0
        limit, last_step = tol * tol, 0.0
        while math.isfinite(obj) and iters < max_iter:
            iters += 1
            damped = hess + np.diag(np.diag(hess) * lam + 1e-12)
            try:
                chol = np.linalg.cholesky(damped)
                delta = np.linalg.solve(chol.T, np.linalg.solve(chol, grad))
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > _LAM_MAX:
                    break
                continue
            grad_delta = grad @ delta
            if grad_delta <= limit and lam <= 1e-2:
                converged = True
                break
            if lam <= 1e-2 and grad_delta <= 1.0 and grad_delta**2 <= limit * last_step:
                p, converged = np.clip(p + delta, lower, upper), True  # the free last step
                break
            p_try = np.clip(p + delta, lower, upper)
            obj_try, obj_try_w, h_try, g_try, mu_try = _objective(
                d, p_try, shape, method, s2, scale, mu_ref
            )
            if obj_try < obj:
                decrease = obj - obj_try
                p, hess, grad, mu_ref, obj = p_try, h_try, g_try, mu_try, obj_try_w
                last_step = grad_delta if lam <= 1e-2 else 0.0
                lam = max(lam * 0.1, 1e-7)
                if decrease <= limit:
                    converged = True
                    break
            else:
                lam *= 10.0
                if lam > _LAM_MAX:
                    break
        # the bounds come from the last evaluated iterate's information (LSQ: Fisher's at p)
        _, _, fisher, _, mu = _objective(d, p, shape, MLE, s2, scale, None)
        if method != LSQ and hess is not None:
            fisher = hess
        theta = _natural(p)
        inner = (p <= lower) | (p >= upper)
        inner[3] = False
        converged = converged and not inner.any()
        try:
            cov = np.linalg.inv(fisher)
            errors = np.sqrt(np.diag(cov)) * np.array(
                [1, 1, 1, 1, theta[4], theta[5], 1 - theta[6] ** 2]
            )
        except np.linalg.LinAlgError:
            errors = np.full(7, np.nan)
            converged = False
        if not (errors[0] < max(h, w) and errors[1] < max(h, w)):
            converged = False
        m, ds = mu + s2, d + s2
        pos = ds > 0
        lgam = np.array([math.lgamma(v + 1.0) if v > 0 else 0.0 for v in ds])
        loglik = np.sum(np.where(pos, ds * np.log(m) - m - lgam, -m))
        chi2 = np.sum((d - mu) ** 2 / m)
        for arr, value in zip(out, (theta, errors, loglik, chi2, iters, converged), strict=True):
            arr[k] = value
    return out

"""numba kernel: the Levenberg–Marquardt fits of two Gaussians of eq. 1 over one background.

`pair_fits` runs the iterations of :mod:`latentz.fit.pairs` (13 internal parameters: per emitter
``x, y, A, log wx, log wy, atanh rho``, then the shared background) for each row of a batch, in
parallel over rows. Its NumPy twin is :func:`latentz.fit.pairs._levenberg_marquardt`: the same
model, Fisher scoring matrix, damping schedule, bounds and stopping rule, vectorised over rows;
the two differ by rounding only (the order of the sums, and a Cholesky solve where NumPy takes
LAPACK's LU).

The model and its derivatives are kept parameter-major, ``jac[a, k]`` for parameter ``a`` at
pixel ``k``, so that each entry of the Fisher matrix is a dot product over contiguous pixels.
A trial step is evaluated with its derivatives, which the next iteration uses when it is taken.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from latentz.fit._kernels import _FASTMATH, cholesky_solver

#: Internal parameters of a pair: per emitter x, y, A, log wx, log wy, atanh rho; the background.
N_PAIR = 13
_LAM0 = 1e-3
_LAM_STOP = 1e8
_LOG_FLOOR = 1e-12
_cholesky, _solve = cholesky_solver(N_PAIR)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _model(theta, h, w, mu, jac):
    """Expected counts ``mu`` (p,) at internal parameters ``theta`` (13,) and their
    derivatives ``jac`` (13, p), over ``h`` x ``w`` pixels (row-major, pixel ``[i, j]`` at
    ``x = j, y = i``)."""
    for k in range(h * w):
        mu[k] = theta[12]
        jac[12, k] = 1.0
    for e in range(0, 12, 6):
        x = theta[e]
        y = theta[e + 1]
        amp = theta[e + 2]
        iwx = 1.0 / math.exp(theta[e + 3])
        iwy = 1.0 / math.exp(theta[e + 4])
        rho = math.tanh(theta[e + 5])
        iom = 1.0 / (1.0 - rho * rho)
        for i in range(h):
            v = (i - y) * iwy
            for j in range(w):
                k = i * w + j
                u = (j - x) * iwx
                a = (u - rho * v) * iom
                b = (v - rho * u) * iom
                q = u * a + v * b
                g = math.exp(-0.5 * q)
                ag = amp * g
                mu[k] += ag
                jac[e, k] = ag * a * iwx
                jac[e + 1, k] = ag * b * iwy
                jac[e + 2, k] = g
                jac[e + 3, k] = ag * u * a
                jac[e + 4, k] = ag * v * b
                jac[e + 5, k] = ag * (u * v - rho * q)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _loglik(data, seen, mu, s2):
    """``sum d' log mu' - mu'`` with ``d' = d + s2``, ``mu' = mu + s2`` over the ``seen`` pixels
    (1, else 0): the Poisson log-likelihood less its data-only constant."""
    total = 0.0
    for k in range(data.size):
        m = max(mu[k] + s2, _LOG_FLOOR)
        total += seen[k] * ((data[k] + s2) * math.log(m) - m)
    return total


@numba.njit(cache=True, fastmath=_FASTMATH)
def _scoring(data, seen, mu, jac, s2, residual, weighted, grad, info):
    """The score ``grad`` (13,) and Fisher matrix ``info`` (13, 13) of the Poisson likelihood at
    the model ``mu`` with derivatives ``jac``; ``residual`` (p,) and ``weighted`` (13, p) are
    work space."""
    p = data.size
    for k in range(p):
        m = max(mu[k] + s2, _LOG_FLOOR)
        residual[k] = seen[k] * ((data[k] + s2) / m - 1.0)
        weight = seen[k] / m
        for a in range(N_PAIR):
            weighted[a, k] = weight * jac[a, k]
    for a in range(N_PAIR):
        total = 0.0
        for k in range(p):
            total += residual[k] * jac[a, k]
        grad[a] = total
        for b in range(a + 1):
            total = 0.0
            for k in range(p):
                total += weighted[a, k] * jac[b, k]
            info[a, b] = total
            info[b, a] = total


@numba.njit(cache=True, fastmath=_FASTMATH)
def _damped_step(info, grad, damping, damped, factor, step):
    """Solve ``(I + diag(damping I_kk + 1e-9 (I_kk + 1))) step = grad`` by Cholesky into
    ``step``; False where the matrix is not positive definite. ``damped`` receives the matrix's
    lower triangle, ``factor`` its Cholesky factor."""
    for i in range(N_PAIR):
        for j in range(i):
            damped[i, j] = info[i, j]
        damped[i, i] = info[i, i] + (damping * info[i, i] + 1e-9 * (info[i, i] + 1.0))
    if not _cholesky(damped, factor):
        return False
    _solve(factor, grad, step)
    return True


@numba.njit(cache=True, fastmath=_FASTMATH)
def _fit_row(data, seen, theta, lo, hi, h, w, s2, max_iter, tol, pixels, work, mats, vecs):
    """Fit one row from ``theta`` (13, internal; updated in place); returns (loglik, converged,
    iterations). Work space: ``pixels`` (3, p) the model at ``theta``, at the trial and the
    residuals; ``work`` (3, 13, p) their derivatives and the weighted derivatives; ``mats``
    (3, 13, 13) the Fisher matrix, the damped system and its factor; ``vecs`` (3, 13)."""
    jac, jac_try, weighted = work[0], work[1], work[2]
    mu, mu_try, residual = pixels[0], pixels[1], pixels[2]
    info, damped, factor = mats[0], mats[1], mats[2]
    grad, step, trial = vecs[0], vecs[1], vecs[2]
    _model(theta, h, w, mu, jac)
    loglik = _loglik(data, seen, mu, s2)
    damping = _LAM0
    converged = False
    iterations = 0
    fresh = True  # mu and jac hold theta's model, not yet turned into the score
    for _ in range(max_iter):
        iterations += 1
        if fresh:
            _scoring(data, seen, mu, jac, s2, residual, weighted, grad, info)
            fresh = False
        solved = _damped_step(info, grad, damping, damped, factor, step)
        better = False
        small = solved
        if solved:
            for a in range(N_PAIR):
                trial[a] = min(max(theta[a] + step[a], lo[a]), hi[a])
                small = small and step[a] * step[a] * info[a, a] <= tol * tol
            _model(trial, h, w, mu_try, jac_try)
            new = _loglik(data, seen, mu_try, s2)
            better = new > loglik
            if better:
                for a in range(N_PAIR):
                    theta[a] = trial[a]
                loglik = new
                jac, jac_try = jac_try, jac
                mu, mu_try = mu_try, mu
                fresh = True
        damping = damping / 10.0 if better else damping * 10.0
        converged = small
        if small or damping > _LAM_STOP:
            break
    return loglik, converged, iterations


@numba.njit(parallel=True, nogil=True, cache=True)
def pair_fits(data, seen, theta, lo, hi, h, w, s2, max_iter, tol, n_chunks, loglik, converged,
              iterations):  # fmt: skip
    """Fit every row of ``data`` (n, h * w photoelectrons, ``seen`` 1 where the pixel is in the
    frame, else 0) from ``theta`` (n, 13, internal, updated in place) within the box ``lo``,
    ``hi``; read-noise variance ``s2``; stop within ``tol`` Cramér–Rao bounds or after
    ``max_iter`` iterations. Writes each row's log-likelihood (less its data-only constant),
    whether the last step was within ``tol``, and its iterations. Rows are split into
    ``n_chunks`` contiguous chunks that share work buffers."""
    n = data.shape[0]
    p = h * w
    for c in numba.prange(n_chunks):
        pixels = np.empty((3, p))
        work = np.empty((3, N_PAIR, p))
        mats = np.empty((3, N_PAIR, N_PAIR))
        vecs = np.empty((3, N_PAIR))
        for r in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            loglik[r], converged[r], iterations[r] = _fit_row(
                data[r], seen[r], theta[r], lo, hi, h, w, s2, max_iter, tol, pixels, work, mats,
                vecs,
            )  # fmt: skip

"""numba kernels: batched Levenberg–Marquardt fits of eq. 1, parallel over ROIs.

One compiled kernel, `fit_batch`, serves all three estimators (``method`` is an integer argument,
not a specialisation). It takes float64 ROIs in photoelectrons and writes into arrays that the
Python wrapper allocated. The NumPy reference twin is :func:`latentz.fit._reference.fit_reference`.

Parameters inside the kernel are internal (``x, y, A, B, log wx, log wy, atanh rho``); see
:mod:`._model` for the model and its derivatives.

Estimators (``s2`` is the read-noise variance in photoelectrons squared):

``LSQ``   minimise ``sum (d - mu)^2`` (scaled by a per-ROI constant so that the objective is in
          chi-square units; the solution is unchanged).
``WLSQ``  light-weighting: minimise ``sum (d - mu)^2 / (mu_k + s2)`` with weights from the model
          ``mu_k`` of the last accepted iterate, recomputed after every accepted step. At its fixed
          point the weighted normal equations equal the Poisson score equations.
``MLE``   minimise the Poisson deviance of ``d + s2 ~ Poisson(mu + s2)`` by Fisher scoring.

All three take the Levenberg–Marquardt step ``(H + lam diag H) delta = g`` with ``H`` the
(weighted) Gauss–Newton / Fisher matrix and ``g`` half the negative gradient, project it onto
the parameter box, and accept it only if the objective decreases. A fit has converged when the
next step, undamped, is at most ``tol`` Cramér–Rao bounds long, ``delta' H delta <= tol^2``, or
when an accepted step lowered the objective by at most ``tol^2``. For WLSQ and MLE ``H`` is the
Fisher information, so ``delta' H delta`` is the squared distance from the optimum in units of
the bounds (no parameter is more than ``sqrt(delta' H delta)`` of its own bounds away), and a
full step lowers the objective by just that much; for LSQ ``H`` is scaled to the mean pixel
variance. Fisher scoring shrinks the distance to the optimum about tenfold per step near it
(0.07 median, 0.37 at the 99th percentile on the benchmark's ROIs). So the last step is taken
without evaluating it when it is at most one bound long and the step after it, estimated as
this one shrunk once more by the factor the last accepted step shrank by, would be within
``tol``: the model is then computed once more, without derivatives, for the log-likelihood and
chi-square, and the bounds are those of the last evaluated iterate, at most one bound away. With
the default ``tol`` a fit typically evaluates the model and its Fisher matrix three times and
ends within 0.01 bounds of the optimum (all within 0.035 on the benchmark's ROIs).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

LSQ, WLSQ, MLE = 0, 1, 2
_NP = 7
_LAM0 = 1e-3
_LAM_MAX = 1e10
_FASTMATH = {"nsz", "arcp", "contract", "reassoc"}
#: Largest ``q / 2`` at a row's ends for which `_row_start`'s recurrence is used.
_EXP_RANGE = 600.0
#: Largest ``|t|`` for which `_atanh_series` stands in for a logarithm.
_SERIES_MAX = 0.1


@numba.njit(cache=True, fastmath=_FASTMATH)
def _border_mean(roi):
    """Mean of the ROI's border pixels: the start's background."""
    h, w = roi.shape
    border = 0.0
    for j in range(w):
        border += roi[0, j] + roi[h - 1, j]
    for i in range(1, h - 1):
        border += roi[i, 0] + roi[i, w - 1]
    return border / (2 * w + 2 * (h - 2))


@numba.njit(cache=True, fastmath=_FASTMATH)
def _box_sum(roi, bg, i, j):
    """Sum of the background-subtracted pixels of the 3 x 3 box at ``(i, j)`` inside the ROI."""
    h, w = roi.shape
    s = 0.0
    for di in range(-1, 2):
        for dj in range(-1, 2):
            ii = i + di
            jj = j + dj
            if 0 <= ii < h and 0 <= jj < w:
                s += roi[ii, jj] - bg
    return s


@numba.njit(cache=True, fastmath=_FASTMATH)
def _start_at(roi, bg, i0, j0, out):
    """Moment-based start (natural parameters) with the spot's peak at pixel ``(i0, j0)`` over
    the background ``bg``: position from the peak's 3 x 3 box, widths from the ROI's moments and
    its signal over the peak (see `_model.moment_start`)."""
    h, w = roi.shape
    signal = 0.0
    for i in range(h):
        for j in range(w):
            signal += roi[i, j] - bg
    peak = max(roi[i0, j0] - bg, _box_sum(roi, bg, i0, j0) / 9.0)
    tot = 0.0
    sx = 0.0
    sy = 0.0
    for i in range(max(i0 - 1, 0), min(i0 + 2, h)):
        for j in range(max(j0 - 1, 0), min(j0 + 2, w)):
            p = max(roi[i, j] - bg, 0.0)
            tot += p
            sx += p * j
            sy += p * i
    x0 = sx / tot if tot > 0 else float(j0)
    y0 = sy / tot if tot > 0 else float(i0)
    tot = 0.0
    vxx = 0.0
    vyy = 0.0
    vxy = 0.0
    for i in range(h):
        for j in range(w):
            p = max(roi[i, j] - bg, 0.0)
            dx = j - x0
            dy = i - y0
            tot += p
            vxx += p * dx * dx
            vyy += p * dy * dy
            vxy += p * dx * dy
    if tot > 0:
        vxx /= tot
        vyy /= tot
        vxy /= tot
    wmax = 0.5 * min(h, w)
    rho = 0.0
    aspect = 1.0
    if vxx > 0 and vyy > 0:
        rho = min(max(vxy / math.sqrt(vxx * vyy), -0.8), 0.8)
        aspect = min(max(math.sqrt(vxx / vyy), 0.5), 2.0)
    amp = max(peak, 1e-3)
    area = max(signal, amp) / (2.0 * math.pi * amp * math.sqrt(1.0 - rho * rho))
    area = min(max(area, 0.25), wmax * wmax)
    out[0] = x0
    out[1] = y0
    out[2] = amp
    out[3] = bg
    out[4] = min(max(math.sqrt(area * aspect), 0.5), wmax)
    out[5] = min(max(math.sqrt(area / aspect), 0.5), wmax)
    out[6] = rho


@numba.njit(cache=True, fastmath=_FASTMATH)
def _start(roi, out):
    """Moment-based start (natural parameters) at the ROI's brightest 3 x 3 box — twin of
    `_model.moment_start`."""
    h, w = roi.shape
    bg = _border_mean(roi)
    best = -np.inf
    i0 = 0
    j0 = 0
    for i in range(h):
        for j in range(w):
            s = _box_sum(roi, bg, i, j)
            if s > best:
                best = s
                i0 = i
                j0 = j
    _start_at(roi, bg, i0, j0, out)


@numba.njit(cache=True, fastmath=_FASTMATH)
def log_factorial(d):
    """``log Gamma(d + 1)`` for real ``d > -1``: Stirling's series at ``z = d + 1 >= 8``
    (truncation error below ``1 / (1188 z^9) < 1e-11``), shifted up by the recurrence below.

    About twice as fast as ``math.lgamma``, which dominated the final pass of a fit.
    """
    z = d + 1.0
    shift = 0.0
    if z < 8.0:
        prod = 1.0
        while z < 8.0:
            prod *= z
            z += 1.0
        shift = math.log(prod)
    iz = 1.0 / z
    iz2 = iz * iz
    series = iz * (1.0 / 12.0 - iz2 * (1.0 / 360.0 - iz2 * (1.0 / 1260.0 - iz2 / 1680.0)))
    return (z - 0.5) * math.log(z) - z + 0.9189385332046727 + series - shift


@numba.njit(cache=True, fastmath=_FASTMATH)
def _row_start(v, x, w, rho, iom, iwx):
    """``exp(-q / 2)`` at the first pixel of a row, the ratio to the next pixel, and whether the
    row must be computed pixel by pixel instead (returned as ``(g, ratio, direct)``).

    Along a row ``q`` is quadratic in the column, so the ratio between neighbours changes by the
    constant factor ``exp(-iom / wx^2)``. ``exp(-q / 2)`` is log-concave, so its smallest value
    on the row is at an end: where both ends lie above ``exp(-600)``, no value or ratio of the
    row leaves float64's normal range.
    """
    u0 = -x * iwx
    u1 = (w - 1 - x) * iwx
    e0 = 0.5 * iom * (u0 * u0 - 2.0 * rho * u0 * v + v * v)
    e1 = 0.5 * iom * (u1 * u1 - 2.0 * rho * u1 * v + v * v)
    if e0 > _EXP_RANGE or e1 > _EXP_RANGE:
        return 0.0, 0.0, True
    ratio = math.exp(-0.5 * iom * iwx * (2.0 * u0 + iwx - 2.0 * rho * v))
    return math.exp(-e0), ratio, False


@numba.njit(cache=True, fastmath=_FASTMATH)
def _atanh_series(t):
    """``2 atanh(t) = log((1 + t) / (1 - t))`` for ``|t| <= 0.1``, relative error below 1e-13."""
    t2 = t * t
    return 2.0 * t * (1.0 + t2 * (1 / 3 + t2 * (1 / 5 + t2 * (1 / 7 + t2 * (1 / 9 + t2 / 11)))))


@numba.njit(cache=True, fastmath=_FASTMATH)
def _log_ratio(new, old, inv_old):
    """``log(new / old)`` for positive ``new`` and ``old`` (``inv_old = 1 / old``): the series of
    ``2 atanh(t)``, ``t = (new - old) / (new + old)``, where ``|t| <= 0.1``, else ``math.log``."""
    t = (new - old) / (new + old)
    if abs(t) > _SERIES_MAX:
        return math.log(new * inv_old)
    return _atanh_series(t)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _log_likelihood(roi, mu, weight, s2):
    """``sum d log m - m - log(d!)`` over the pixels of ``d + s2 ~ Poisson(m + s2)``, with the
    model ``mu`` (row-major) and ``weight = 1 / (mu + s2)``; ``-m`` where ``d <= 0``.

    Where ``d >= 8``, Stirling's series for ``log(d!)`` (truncation below ``1e-11``) leaves
    ``d log(m / d)`` (`_log_ratio`: no logarithm where ``m`` is within about 20 % of ``d``) and
    ``log d``, summed as the log of the product.
    """
    h, w = roi.shape
    total = 0.0
    n_series = 0
    product = 1.0
    log_product = 0.0
    for i in range(h):
        for j in range(w):
            m = mu[i * w + j] + s2
            d = roi[i, j] + s2
            if 8.0 <= d < 1e100:
                inv = 1.0 / d
                inv2 = inv * inv
                series = inv * (1 / 12 - inv2 * (1 / 360 - inv2 * (1 / 1260 - inv2 / 1680)))
                total += d * _log_ratio(m, d, inv) - m + d - series
                n_series += 1
                product *= d
                if product > 1e200:
                    log_product += math.log(product)
                    product = 1.0
            elif d > 0.0:
                total += d * math.log(m) - m - log_factorial(d)
            else:
                total -= m
    log_product += math.log(product)
    return total - 0.5 * (log_product + n_series * 1.8378770664093453)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _chi_square(roi, mu, weight):
    """Pearson chi-square ``sum (d - mu)^2 weight`` (``weight = 1 / (mu + s2)``, row-major)."""
    h, w = roi.shape
    total = 0.0
    for i in range(h):
        for j in range(w):
            r = roi[i, j] - mu[i * w + j]
            total += r * r * weight[i * w + j]
    return total


@numba.njit(cache=True, fastmath=_FASTMATH)
def _far_deviance(roi, s2, mu_ref, w_ref, mu, weight):
    """The deviance change, from ``mu_ref`` to ``mu``, of the pixels that `_evaluate` marked by a
    negative ``weight`` (a model moved too far for `_atanh_series`); unmarks them."""
    h, w = roi.shape
    total = 0.0
    for i in range(h):
        for j in range(w):
            k = i * w + j
            if weight[k] < 0.0:
                weight[k] = -weight[k]
                new = mu[k] + s2
                total += 2.0 * (new - mu_ref[k] - s2 - (roi[i, j] + s2) * math.log(new * w_ref[k]))
    return total


@numba.njit(cache=True, fastmath=_FASTMATH)
def _evaluate(
    roi, p, method, s2, scale, mu_ref, w_ref, mu_out, w_out, hess, grad, full=True, hessian=True
):
    """Objective at internal parameters ``p``, with ``hess`` and ``grad`` for the next step.

    Returns ``(objective with the reference weights, objective with the weights at p)``; they
    differ only for WLSQ, whose reference weights are ``w_ref``. ``mu_out`` and ``w_out`` receive
    the model and the weights ``1 / (mu + s2)`` at ``p`` (row-major). For MLE the objective is the
    change of the Poisson deviance from the reference model ``mu_ref`` (weights ``w_ref``), so
    that the objective at the reference itself is 0: the deviance change needs no logarithm per
    pixel where the two models differ by little (`_log_ratio`), and stays well above float64
    rounding near the optimum. Passing ``mu_out`` as ``mu_ref`` gives 0 at ``p``.

    ``exp(-q / 2)`` is evaluated two exponentials per row: along a row ``q`` is quadratic in the
    column, so each pixel's value is the previous one times a ratio that itself changes by a
    constant factor (`_row_start`), wherever no value of the row falls below ``exp(-600)``.

    With ``full`` False only ``mu_out`` and ``w_out`` are written (for every method), and
    ``(0, 0)`` is returned; with ``hessian`` False, ``hess`` is not, nor for MLE the objective
    (returned as 0): the score alone, a quarter of the per-pixel sums.
    """
    h, w = roi.shape
    x = p[0]
    y = p[1]
    amp = p[2]
    bg = p[3]
    wx = math.exp(p[4])
    wy = math.exp(p[5])
    rho = math.tanh(p[6])
    om = 1.0 - rho * rho
    iom = 1.0 / om
    iwx = 1.0 / wx
    iwy = 1.0 / wy
    # exp(-q / 2) of every pixel into mu_out first: the accumulation loop below then calls no
    # function, which would force its accumulators out of the registers
    step_ratio = math.exp(-iom * iwx * iwx)
    for i in range(h):
        v = (i - y) * iwy
        g, ratio, direct = _row_start(v, x, w, rho, iom, iwx)
        for j in range(w):
            if direct:
                u = (j - x) * iwx
                g = math.exp(-0.5 * iom * (u * u - 2.0 * rho * u * v + v * v))
            mu_out[i * w + j] = g
            g *= ratio
            ratio *= step_ratio
    g0 = g1 = g2 = g3 = g4 = g5 = g6 = 0.0
    h00 = h01 = h02 = h03 = h04 = h05 = h06 = 0.0
    h11 = h12 = h13 = h14 = h15 = h16 = 0.0
    h22 = h23 = h24 = h25 = h26 = 0.0
    h33 = h34 = h35 = h36 = 0.0
    h44 = h45 = h46 = 0.0
    h55 = h56 = h66 = 0.0
    obj_ref = 0.0
    obj_new = 0.0
    far = False  # some pixel's model moved too far for the series: its log is added below
    for i in range(h):
        v = (i - y) * iwy
        for j in range(w):
            k = i * w + j
            g = mu_out[k]
            ag = amp * g
            mu = ag + bg
            mu_out[k] = mu
            if not full:
                w_out[k] = 1.0 / (mu + s2)
                continue
            u = (j - x) * iwx
            a = (u - rho * v) * iom
            b = (v - rho * u) * iom
            q = u * a + v * b
            d = roi[i, j]
            if method == MLE:
                mus = mu + s2
                if mus <= 0.0:
                    return np.inf, np.inf
                ds = d + s2
                wt = 1.0 / mus
                w_out[k] = wt
                old = mu_ref[k] + s2
                if ds > 0.0:
                    if hessian:  # the score alone needs no objective
                        t = (mus - old) / (mus + old)
                        if abs(t) <= _SERIES_MAX:
                            obj_ref += 2.0 * (mus - old - ds * _atanh_series(t))
                        else:
                            w_out[k] = -wt
                            far = True
                    res = ds * wt - 1.0
                else:
                    if hessian:
                        obj_ref += 2.0 * (mus - old)
                    res = -1.0
            elif method == WLSQ:
                r = d - mu
                wt = 1.0 / (mu + s2)
                w_out[k] = wt
                obj_ref += r * r * w_ref[k]
                obj_new += r * r * wt
                res = r * wt
            else:
                r = d - mu
                wt = scale
                obj_ref += r * r * scale
                res = r * scale
            j0 = ag * a * iwx
            j1 = ag * b * iwy
            j4 = ag * u * a
            j5 = ag * v * b
            j6 = ag * (u * v - rho * q)
            g0 += j0 * res
            g1 += j1 * res
            g2 += g * res
            g3 += res
            g4 += j4 * res
            g5 += j5 * res
            g6 += j6 * res
            if not hessian:
                continue
            w0 = wt * j0
            w1 = wt * j1
            w2 = wt * g
            w4 = wt * j4
            w5 = wt * j5
            w6 = wt * j6
            h00 += w0 * j0
            h01 += w0 * j1
            h02 += w0 * g
            h03 += w0
            h04 += w0 * j4
            h05 += w0 * j5
            h06 += w0 * j6
            h11 += w1 * j1
            h12 += w1 * g
            h13 += w1
            h14 += w1 * j4
            h15 += w1 * j5
            h16 += w1 * j6
            h22 += w2 * g
            h23 += w2
            h24 += w2 * j4
            h25 += w2 * j5
            h26 += w2 * j6
            h33 += wt
            h34 += w4
            h35 += w5
            h36 += w6
            h44 += w4 * j4
            h45 += w4 * j5
            h46 += w4 * j6
            h55 += w5 * j5
            h56 += w5 * j6
            h66 += w6 * j6
    # Scalar accumulators (not array elements) let LLVM keep the sums in registers.
    grad[0] = g0
    grad[1] = g1
    grad[2] = g2
    grad[3] = g3
    grad[4] = g4
    grad[5] = g5
    grad[6] = g6
    if hessian:
        hess[0, 0] = h00
        hess[0, 1] = h01
        hess[0, 2] = h02
        hess[0, 3] = h03
        hess[0, 4] = h04
        hess[0, 5] = h05
        hess[0, 6] = h06
        hess[1, 1] = h11
        hess[1, 2] = h12
        hess[1, 3] = h13
        hess[1, 4] = h14
        hess[1, 5] = h15
        hess[1, 6] = h16
        hess[2, 2] = h22
        hess[2, 3] = h23
        hess[2, 4] = h24
        hess[2, 5] = h25
        hess[2, 6] = h26
        hess[3, 3] = h33
        hess[3, 4] = h34
        hess[3, 5] = h35
        hess[3, 6] = h36
        hess[4, 4] = h44
        hess[4, 5] = h45
        hess[4, 6] = h46
        hess[5, 5] = h55
        hess[5, 6] = h56
        hess[6, 6] = h66
        for k in range(_NP):
            for m in range(k + 1, _NP):
                hess[m, k] = hess[k, m]
    if far:
        obj_ref += _far_deviance(roi, s2, mu_ref, w_ref, mu_out, w_out)
    if method == LSQ:
        obj_new = obj_ref
    return obj_ref, obj_new


def cholesky_solver(n: int) -> tuple[Any, Any]:
    """``cholesky(a, lower)``, the Cholesky factor of the symmetric ``n`` x ``n`` matrix ``a``
    (its lower triangle is read) into ``lower``, False if not positive definite, and
    ``solve(lower, b, out)``, the solution of ``L L^T out = b`` from that factor; compiled with
    ``n`` a constant, as the fixed-size loops of the hot path were."""

    @numba.njit(cache=True, fastmath=_FASTMATH)
    def cholesky(a, lower):
        for i in range(n):
            for j in range(i + 1):
                s = a[i, j]
                for k in range(j):
                    s -= lower[i, k] * lower[j, k]
                if i == j:
                    if not s > 0.0:
                        return False
                    lower[i, i] = math.sqrt(s)
                else:
                    lower[i, j] = s / lower[j, j]
        return True

    @numba.njit(cache=True, fastmath=_FASTMATH)
    def solve(lower, b, out):
        for i in range(n):
            s = b[i]
            for k in range(i):
                s -= lower[i, k] * out[k]
            out[i] = s / lower[i, i]
        for i in range(n - 1, -1, -1):
            s = out[i]
            for k in range(i + 1, n):
                s -= lower[k, i] * out[k]
            out[i] = s / lower[i, i]

    return cholesky, solve


_cholesky, _solve = cholesky_solver(_NP)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _inverse_diagonal(lower, work, out):
    """Diagonal of ``(L L^T)^-1`` into ``out`` from the Cholesky factor ``L = lower``, through
    ``M = L^-1`` (lower triangular, into ``work``): ``(L L^T)^-1 = M^T M``."""
    n = _NP
    for i in range(n):
        work[i, i] = 1.0 / lower[i, i]
        for j in range(i):
            s = 0.0
            for k in range(j, i):
                s += lower[i, k] * work[k, j]
            work[i, j] = -s * work[i, i]
    for j in range(n):
        s = 0.0
        for i in range(j, n):
            s += work[i, j] * work[i, j]
        out[j] = s


@numba.njit(cache=True, fastmath=_FASTMATH)
def _fit_one(
    roi, start, lower_b, upper_b, method, s2, max_iter, tol, scratch, vecs, mats, out_p, out_e
):
    """Fit one ROI from the natural-parameter ``start``; return (loglik, chi2, iters, converged).

    Work arrays, allocated once per chunk of ROIs: ``scratch`` (4, h*w) holds the model and the
    weights at the current and at the trial parameters; ``vecs`` (7, 7) and ``mats`` (3, 7, 7)
    the rest.
    """
    h, w = roi.shape
    npix = h * w
    mu_ref = scratch[0]
    mu_try = scratch[1]
    w_ref = scratch[2]
    w_try = scratch[3]
    hess = mats[0]
    hess_try = mats[1]
    lower = mats[2]
    grad = vecs[0]
    grad_try = vecs[1]
    delta = vecs[2]
    p = vecs[3]
    p_try = vecs[4]
    p[0] = start[0]
    p[1] = start[1]
    p[2] = start[2]
    p[3] = start[3]
    p[4] = math.log(start[4])
    p[5] = math.log(start[5])
    p[6] = math.atanh(start[6])
    for k in range(_NP):
        p[k] = min(max(p[k], lower_b[k]), upper_b[k])
    scale = 0.0
    if method == LSQ:
        for i in range(h):
            for j in range(w):
                scale += roi[i, j] + s2
        scale = 1.0 / max(scale / npix, 1.0)
    # The start is its own reference: WLSQ's first weights are its own, MLE's objective is 0.
    obj = _evaluate(roi, p, method, s2, scale, mu_ref, w_ref, mu_ref, w_ref, hess, grad)[1]
    converged = False
    free_step = False
    lam = _LAM0
    iters = 0
    if math.isfinite(obj):
        limit = tol * tol
        last_step = 0.0  # squared length of the last accepted step if undamped, else 0
        while iters < max_iter:
            iters += 1
            for k in range(_NP):
                for m in range(_NP):
                    hess_try[k, m] = hess[k, m]
                hess_try[k, k] = hess[k, k] * (1.0 + lam) + 1e-12
            if not _cholesky(hess_try, lower):
                lam *= 10.0
                if lam > _LAM_MAX:
                    break
                continue
            _solve(lower, grad, delta)
            predicted = 0.0
            for k in range(_NP):
                predicted += grad[k] * delta[k]
            if lam <= 1e-2:
                if predicted <= limit:
                    converged = True
                    break
                if predicted <= 1.0 and predicted * predicted <= limit * last_step:
                    # The last step shrank to this one; the next would shrink as much again, to
                    # within tol: take this one without evaluating it.
                    for k in range(_NP):
                        p[k] = min(max(p[k] + delta[k], lower_b[k]), upper_b[k])
                    free_step = True
                    converged = True
                    break
            for k in range(_NP):
                p_try[k] = min(max(p[k] + delta[k], lower_b[k]), upper_b[k])
            obj_try, obj_try_w = _evaluate(
                roi, p_try, method, s2, scale, mu_ref, w_ref, mu_try, w_try, hess_try, grad_try
            )
            if obj_try < obj:
                decrease = obj - obj_try
                for k in range(_NP):
                    p[k] = p_try[k]
                    grad[k] = grad_try[k]
                    for m in range(_NP):
                        hess[k, m] = hess_try[k, m]
                for k in range(npix):
                    mu_ref[k] = mu_try[k]
                    w_ref[k] = w_try[k]
                obj = obj_try_w
                last_step = predicted if lam <= 1e-2 else 0.0
                lam = max(lam * 0.1, 1e-7)
                if decrease <= limit:
                    converged = True
                    break
            else:
                lam *= 10.0
                if lam > _LAM_MAX:
                    break
    if free_step and method != LSQ:
        _evaluate(roi, p, method, s2, scale, mu_ref, w_ref, mu_ref, w_ref, hess_try, grad, False)
    return _finish(
        roi, p, lower_b, upper_b, method, s2, scale, scratch, hess, grad, mats, vecs,
        converged, iters, out_p, out_e,
    )  # fmt: skip


@numba.njit(cache=True)
def to_internal(natural, p, scale):
    """Write the internal parameters (x, y, A, B, log wx, log wy, atanh rho) of ``natural`` into
    ``p``, and into ``scale`` d natural / d internal (1, 1, 1, 1, wx, wy, 1 - rho^2), which takes
    an information or covariance from one to the other."""
    for m in range(4):
        p[m] = natural[m]
        scale[m] = 1.0
    p[4] = math.log(natural[4])
    p[5] = math.log(natural[5])
    p[6] = math.atanh(natural[6])
    scale[4] = natural[4]
    scale[5] = natural[5]
    scale[6] = 1.0 - natural[6] * natural[6]


@numba.njit(parallel=True, nogil=True, cache=True)
def fisher_batch(params, h, w, s2, n_chunks, out):
    """Fisher information (n, 7, 7) in the *natural* parameters of eq. 1 at each row of
    ``params`` (n, 7, natural) in an ``h`` x ``w`` ROI with read-noise variance ``s2``, written
    into ``out``: ``sum grad(mu) grad(mu)^T / (mu + s2)``, the kernel twin of
    :func:`latentz.fit._model.fisher_information` (`_evaluate`'s information, which does not
    depend on the data, rescaled from the internal parameters)."""
    n = params.shape[0]
    for c in numba.prange(n_chunks):
        roi = np.zeros((h, w))
        scratch = np.zeros((4, h * w))
        grad = np.empty(_NP)
        p = np.empty(_NP)
        scale = np.empty(_NP)
        for k in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            to_internal(params[k], p, scale)
            info = out[k]
            _evaluate(roi, p, WLSQ, s2, 1.0, scratch[0], scratch[1], scratch[2], scratch[3],
                      info, grad)  # fmt: skip
            for a in range(_NP):
                for b in range(_NP):
                    info[a, b] /= scale[a] * scale[b]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _finish(
    roi, p, lower_b, upper_b, method, s2, scale, scratch, hess, grad, mats, vecs,
    converged, iters, out_p, out_e,
):  # fmt: skip
    """Natural parameters, Cramér–Rao bounds, log-likelihood and chi-square at ``p``, whose
    model and weights ``1 / (mu + s2)`` are ``scratch[0]`` and ``scratch[2]``; the bounds are
    those of ``hess`` (for LSQ, of the Fisher information at ``p``)."""
    h, w = roi.shape
    mu = scratch[0]
    weight = scratch[2]
    if method == LSQ:
        # The Fisher information needs the Poisson weights; WLSQ's and MLE's ``hess`` at ``p``
        # already is the Fisher information.
        _evaluate(roi, p, MLE, s2, scale, mu, weight, mu, weight, hess, grad)
    wx = math.exp(p[4])
    wy = math.exp(p[5])
    rho = math.tanh(p[6])
    out_p[0] = p[0]
    out_p[1] = p[1]
    out_p[2] = p[2]
    out_p[3] = p[3]
    out_p[4] = wx
    out_p[5] = wy
    out_p[6] = rho
    for k in range(_NP):
        if k != 3 and (p[k] <= lower_b[k] or p[k] >= upper_b[k]):
            converged = False
    lower = mats[2]
    if _cholesky(hess, lower):
        _inverse_diagonal(lower, mats[1], out_e)
        for k in range(_NP):
            out_e[k] = math.sqrt(out_e[k]) if out_e[k] > 0 else np.nan
        out_e[4] *= wx
        out_e[5] *= wy
        out_e[6] *= 1.0 - rho * rho
        # A position less certain than the ROI is wide (e.g. no spot at all) is no localization.
        if not (out_e[0] < max(h, w) and out_e[1] < max(h, w)):
            converged = False
    else:
        for k in range(_NP):
            out_e[k] = np.nan
        converged = False
    return _log_likelihood(roi, mu, weight, s2), _chi_square(roi, mu, weight), iters, converged


@numba.njit(cache=True, fastmath=_FASTMATH)
def fit_roi(
    k,
    rois,
    start,
    use_start,
    lower_b,
    upper_b,
    method,
    s2,
    max_iter,
    tol,
    scratch,
    vecs,
    mats,
    out_p,
    out_e,
    out_loglik,
    out_chi2,
    out_iter,
    out_conv,
):
    """Fit ROI ``k`` of ``rois`` and write row ``k`` of the outputs (see `fit_batch`).

    The CPU loop of `fit_batch` and the CUDA kernel (:mod:`._cuda`, one thread per ROI) both call
    this function, with work buffers ``scratch`` (4, h*w), ``vecs`` (7, 7), ``mats`` (3, 7, 7).
    """
    roi = rois[k]
    h, w = roi.shape
    finite = True
    for i in range(h):
        for j in range(w):
            if not math.isfinite(roi[i, j]):
                finite = False
    if not finite:
        for m in range(_NP):
            out_p[k, m] = np.nan
            out_e[k, m] = np.nan
        out_loglik[k] = np.nan
        out_chi2[k] = np.nan
        out_iter[k] = 0
        out_conv[k] = False
        return
    first = vecs[6]
    if use_start[k]:
        for m in range(_NP):
            first[m] = start[k, m]
    else:
        _start(roi, first)
    loglik, chi2, iters, conv = _fit_one(
        roi, first, lower_b, upper_b, method, s2, max_iter, tol, scratch, vecs, mats,
        out_p[k], out_e[k],
    )  # fmt: skip
    out_loglik[k] = loglik
    out_chi2[k] = chi2
    out_iter[k] = iters
    out_conv[k] = conv


@numba.njit(parallel=True, nogil=True, cache=True)
def peak_starts(rois, rows, cols, windows, min_side, out):
    """`_start_at` of each ROI of ``rois`` (n, h, w) on its window's pixels (``windows`` (n, 4):
    row_start, row_stop, col_start, col_stop) with its peak at ``(rows[k], cols[k])``, written
    to ``out`` (n, 7) in the whole ROI's pixels, in parallel; NaN for a window narrower than
    ``min_side`` px (one that is not fitted)."""
    for k in numba.prange(rois.shape[0]):
        r0, r1, c0, c1 = windows[k, 0], windows[k, 1], windows[k, 2], windows[k, 3]
        if r1 - r0 < min_side or c1 - c0 < min_side:
            out[k, :] = np.nan
            continue
        roi = rois[k, r0:r1, c0:c1]
        _start_at(roi, _border_mean(roi), rows[k] - r0, cols[k] - c0, out[k])
        out[k, 0] += c0
        out[k, 1] += r0


@numba.njit(parallel=True, nogil=True, cache=True)
def fit_batch(
    rois,
    start,
    use_start,
    lower_b,
    upper_b,
    method,
    s2,
    max_iter,
    tol,
    n_chunks,
    out_p,
    out_e,
    out_loglik,
    out_chi2,
    out_iter,
    out_conv,
):
    """Fit every ROI of ``rois`` (n, h, w) in parallel; outputs are written in place.

    ``start`` (n, 7) holds natural starting values, used where ``use_start`` is true; otherwise
    the moment start is computed. The ROIs are split into ``n_chunks`` contiguous chunks that
    share work buffers. ROIs with a non-finite pixel are skipped: NaN parameters,
    ``converged`` False, 0 iterations.
    """
    n, h, w = rois.shape
    for c in numba.prange(n_chunks):
        scratch = np.empty((4, h * w))
        vecs = np.empty((7, _NP))
        mats = np.empty((3, _NP, _NP))
        for k in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            fit_roi(
                k, rois, start, use_start, lower_b, upper_b, method, s2, max_iter, tol,
                scratch, vecs, mats, out_p, out_e, out_loglik, out_chi2, out_iter, out_conv,
            )  # fmt: skip

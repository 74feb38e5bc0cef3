"""Batches of one-dimensional polynomial models in a scaled Chebyshev basis.

Every local calibration function of the paper (A(z) of order 5, Δx'(z), Δy'(z) and z(shape) of
order 16; Supp. Table 2) is a polynomial per calibration particle. A 16th-order fit in raw
nanometres is ill-conditioned, so each model maps its own domain ``[lo, hi]`` onto ``[-1, 1]`` and
uses Chebyshev polynomials there; the fitted function is the same polynomial the paper writes as
``sum_i C_i z**i``. One :class:`PolyModel` holds ``n`` such polynomials (one per particle) so that
they are fitted and evaluated as arrays, without a Python loop over particles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.polynomial import chebyshev as cheb

from latentz._shared.validate import check_array, check_int

__all__ = ["PolyModel"]


def _scale(x: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Map ``x`` (n, ...) from each row's ``[lo, hi]`` onto ``[-1, 1]``."""
    shape = (domain.shape[0],) + (1,) * (x.ndim - 1)
    lo = domain[:, 0].reshape(shape)
    hi = domain[:, 1].reshape(shape)
    with np.errstate(divide="ignore", invalid="ignore"):  # invalid (NaN) models give NaN
        return (2.0 * x - lo - hi) / (hi - lo)


@numba.njit(nogil=True, cache=True)
def _clenshaw_rows(t: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Each row's Chebyshev series ``coef`` (n, k ≥ 3) at that row's points ``t`` (n, m): the
    Clenshaw recursion of :func:`numpy.polynomial.chebyshev.chebval`, step for step (the same
    bits), without its (n, m) temporary arrays per term, which bound it by memory traffic."""
    n, m = t.shape
    k = coef.shape[1]
    out = np.empty((n, m))
    for r in range(n):
        for j in range(m):
            x = t[r, j]
            x2 = 2 * x
            c0 = coef[r, k - 2]
            c1 = coef[r, k - 1]
            for i in range(3, k + 1):
                tmp = c0
                c0 = coef[r, k - i] - c1
                c1 = tmp + c1 * x2
            out[r, j] = c0 + c1 * x
    return out


@dataclass(frozen=True, eq=False)
class PolyModel:
    """``n`` polynomials, each in the Chebyshev basis of its own scaled domain.

    Parameters
    ----------
    coef : ndarray (n, order + 1)
        Chebyshev coefficients in the scaled variable ``t = (2 x - lo - hi) / (hi - lo)``.
        A row of NaN marks a model that could not be estimated.
    domain : ndarray (n, 2)
        ``[lo, hi]`` of each model, in the units of ``x`` (nm for z, or the shape parameter's).

    Examples
    --------
    >>> z = np.linspace(-3000.0, 3000.0, 61)
    >>> model = PolyModel.from_estimate(z, 1e-3 * z + 2.0, order=3)
    >>> float(np.round(model(np.array([1000.0]))[0], 6))
    3.0
    """

    coef: np.ndarray
    domain: np.ndarray

    def __post_init__(self) -> None:
        coef = np.array(self.coef, dtype=np.float64, ndmin=2)
        domain = np.array(self.domain, dtype=np.float64, ndmin=2)
        if domain.shape != (coef.shape[0], 2):
            raise ValueError(
                f"Expected `domain` to have shape ({coef.shape[0]}, 2), got {domain.shape}."
            )
        coef.setflags(write=False)
        domain.setflags(write=False)
        object.__setattr__(self, "coef", coef)
        object.__setattr__(self, "domain", domain)

    @classmethod
    def from_estimate(
        cls,
        x: Any,
        y: Any,
        *,
        order: int,
        mask: Any = None,
        domain: Any = None,
    ) -> PolyModel:
        """Least-squares fit (uniform weights) of one polynomial per row.

        Parameters
        ----------
        x, y : array_like (n, m) or (m,)
            Abscissae and ordinates; broadcast against each other. Non-finite pairs are ignored.
        order : int
            Polynomial order (>= 0).
        mask : array_like of bool (n, m), optional
            Points to use; the others are ignored.
        domain : array_like (n, 2) or (2,), optional
            Scaling domain; by default each row's extent of the points it uses.

        Returns
        -------
        PolyModel
            Rows with fewer than ``order + 1`` usable points (or a degenerate domain) get NaN
            coefficients.
        """
        order = check_int("order", order, minimum=0)
        xa, ya = np.broadcast_arrays(
            np.atleast_2d(np.asarray(x, dtype=np.float64)),
            np.atleast_2d(np.asarray(y, dtype=np.float64)),
        )
        use = np.isfinite(xa) & np.isfinite(ya)
        if mask is not None:
            use &= np.broadcast_to(np.asarray(mask, dtype=bool), xa.shape)
        n = xa.shape[0]
        if domain is None:
            lo = np.min(np.where(use, xa, np.inf), axis=1)
            hi = np.max(np.where(use, xa, -np.inf), axis=1)
            dom = np.stack([lo, hi], axis=1)
        else:
            dom = np.broadcast_to(np.asarray(domain, dtype=np.float64), (n, 2)).copy()
        ok = (use.sum(axis=1) >= order + 1) & np.all(np.isfinite(dom), axis=1)
        ok &= dom[:, 1] > dom[:, 0]
        safe = np.where(ok[:, None], dom, [[-1.0, 1.0]])
        t = np.where(use, _scale(np.where(use, xa, 0.0), safe), 0.0)
        vander = cheb.chebvander(t, order) * use[..., None]
        rhs = np.where(use, ya, 0.0)
        coef = np.einsum("nkm,nm->nk", np.linalg.pinv(vander), rhs)
        coef[~ok] = np.nan
        return cls(coef, dom)

    @property
    def order(self) -> int:
        """Polynomial order."""
        return self.coef.shape[1] - 1

    @property
    def valid(self) -> np.ndarray:
        """Boolean (n,): which models were estimated."""
        return np.all(np.isfinite(self.coef), axis=1)

    def __len__(self) -> int:
        return self.coef.shape[0]

    def __getitem__(self, index: Any) -> PolyModel:
        """A sub-batch (an integer index keeps one row)."""
        index = np.atleast_1d(np.arange(len(self))[index])
        return PolyModel(self.coef[index], self.domain[index])

    def __call__(self, x: Any) -> np.ndarray:
        """Evaluate: ``x`` of shape (n,) or (n, m) gives one value per row (no range check)."""
        xa = check_array("x", x, ndim=(1, 2), allow_empty=True).astype(np.float64)
        if xa.shape[0] != len(self):
            raise ValueError(f"Expected `x` to have {len(self)} rows, got shape {xa.shape}.")
        t = _scale(xa, self.domain)
        if self.order < 2 or xa.size == 0:
            c = self.coef.T.reshape(self.coef.shape[1], len(self), *([1] * (xa.ndim - 1)))
            return cheb.chebval(t, c, tensor=False)
        rows = np.ascontiguousarray(t.reshape(len(self), -1))
        return _clenshaw_rows(rows, np.ascontiguousarray(self.coef)).reshape(xa.shape)

    def derivative(self) -> PolyModel:
        """The derivative with respect to the unscaled variable (NaN for rows whose domain has
        no width)."""
        if self.order == 0:
            return PolyModel(np.zeros_like(self.coef), self.domain)
        span = self.domain[:, 1] - self.domain[:, 0]
        scale = np.divide(2.0, span, out=np.full_like(span, np.nan), where=span > 0)
        return PolyModel(cheb.chebder(self.coef, axis=1) * scale[:, None], self.domain)

    def shifted(self, offset: Any) -> PolyModel:
        """The same polynomials minus a constant per row (``offset`` of shape (n,))."""
        coef = self.coef.copy()
        coef[:, 0] -= np.broadcast_to(np.asarray(offset, dtype=np.float64), (len(self),))
        return PolyModel(coef, self.domain)

    def contains(self, x: Any) -> np.ndarray:
        """Boolean, same shape as ``x`` (n,) or (n, m): inside each row's domain."""
        xa = np.asarray(x, dtype=np.float64)
        shape = (len(self),) + (1,) * (xa.ndim - 1)
        lo = self.domain[:, 0].reshape(shape)
        hi = self.domain[:, 1].reshape(shape)
        return (xa >= lo) & (xa <= hi)

    def residuals(self, x: Any, y: Any) -> np.ndarray:
        """``y - model(x)`` for data shaped like the fit's."""
        return np.asarray(y, dtype=np.float64) - self(x)

    def leverage(self, x: Any, mask: Any) -> np.ndarray:
        """Each point's leverage h (the diagonal of the hat matrix, 0–1) in the least-squares
        fit of its row to the points ``x`` (n, m) where ``mask`` is True, as
        :meth:`from_estimate` fits them in this model's domain; NaN elsewhere. A point's
        residual scatters by ``sqrt(1 − h)`` times its noise: the fit follows it by ``h``."""
        xa = np.asarray(x, dtype=np.float64)
        use = np.asarray(mask, dtype=bool) & np.isfinite(xa) & self.valid[:, None]
        t = np.where(use, _scale(np.where(use, xa, 0.0), self.domain), 0.0)
        vander = cheb.chebvander(t, self.order) * use[..., None]
        hat = np.einsum("nmk,nkm->nm", vander, np.linalg.pinv(vander))
        return np.where(use, hat, np.nan)

    def coefficients(self) -> np.ndarray:
        """Power-series coefficients ``C_i`` (n, order + 1) in the scaled variable ``t``."""
        k = self.coef.shape[1]
        basis = np.zeros((k, k))
        for j in range(k):
            basis[: j + 1, j] = cheb.cheb2poly(np.eye(k)[j])[: j + 1]
        return self.coef @ basis.T

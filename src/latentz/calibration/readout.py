"""The joint axial readout: z from all of a spot's fitted shape parameters at once.

A spot's fitted q = (wx, wy, ρ) is compared with its calibration particle's curves c(z) of the
same three through focus (:meth:`~latentz.calibration.result.Calibration.curves_at`) by the
Mahalanobis distance

    d²(z) = (q − c(z))ᵀ (C_fit + C_curve)⁻¹ (q − c(z)),

C_fit the covariance of the spot's fitted (wx, wy, ρ) (its own sandwich errors and correlations,
:func:`~latentz.calibration.errors.fit_covariance`; the Cramér–Rao covariance at its fitted
parameters where it carries none) and C_curve the curves' own scatter (diagonal, px², px², 1:
the particle's traces about its curves over its usable planes, where the readout is used).
z minimises d² over the particle's planes, refined by the parabola through the best plane and
its two neighbours. The widths tell how far from focus the spot is, ρ (or wx − wy) on which side:
one shape value that folds them together loses the part of the information that its weights do
not match.

The fit's 1σ in z is the curvature's, ``1 / sqrt(Jᵀ (C_fit + C_curve)⁻¹ J)`` with J = dc/dz at
the minimum; ``spread_nm`` is the farthest plane whose d² lies within 1 of the minimum, which is
σ itself for one clean minimum and reaches a second minimum where there is one (the sign of
defocus unresolved: weak astigmatism, dim spots). Where the curves do not hold the spot (d² at
the minimum beyond :data:`CHI2_HELD`), C is scaled by d²/2 (2 degrees of freedom: 3 values, 1
fitted z), and both σ and the spread grow with it. The minimum is d² at z itself, not at the
best plane: up to half a step from z, that plane's d² also counts the step, which for a bright
spot (σ below the step) would read as curves that do not hold it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["SHAPE_PARAMS", "JointZ", "joint_z", "profile_width", "shape_covariance"]

#: The fitted parameters the readout compares with the calibration curves.
SHAPE_PARAMS = ("wx", "wy", "rho")
#: d² at the minimum beyond which the curves do not hold the spot: χ²(2)'s 99th percentile.
CHI2_HELD = 9.21
#: Values in PARAMS order that stand in for a spot's non-finite ones in the Cramér–Rao
#: covariance (ρ = 1 has none).
_PLACEHOLDER = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
#: Spots searched at once (the distances take spots × planes × 3 values).
_CHUNK = 2048


@dataclass(frozen=True)
class JointZ:
    """The joint readout of n spots on their particles' z axes (nm; NaN where no curve is
    finite).

    Attributes
    ----------
    z_nm : ndarray (n,)
        z at the minimum of d².
    sigma_nm : ndarray (n,)
        The fit's 1σ from the curvature of d² at the minimum.
    spread_nm : ndarray (n,)
        The farthest plane from ``z_nm`` whose d² is within 1 of the minimum.
    """

    z_nm: np.ndarray
    sigma_nm: np.ndarray
    spread_nm: np.ndarray


def shape_covariance(
    params: np.ndarray,
    errors: np.ndarray | None,
    correlations: np.ndarray | None,
    *,
    roi_size: int,
    readnoise: float,
) -> np.ndarray:
    """Covariance (n, 3, 3) of the fitted (wx, wy, ρ) of spots with fitted ``params`` (n, 7, in
    :data:`latentz.fit._model.PARAMS` order): from their ``errors`` (n, 4: amplitude, wx, wy, ρ)
    and ``correlations`` (:func:`~latentz.calibration.errors.fit_covariance`), or, where
    ``errors`` is None, the Cramér–Rao covariance of the Gaussian at the fitted parameters
    centred in a ROI of ``roi_size`` px."""
    from latentz.calibration.errors import fit_covariance
    from latentz.fit._model import PARAMS, covariance

    params = np.array(params, dtype=np.float64)
    if errors is None:
        centred = params.copy()
        centred[:, 0] = centred[:, 1] = (roi_size - 1) / 2
        centred = np.where(np.isfinite(centred), centred, _PLACEHOLDER)  # NaN rows: NaN z
        which = [PARAMS.index(k) for k in SHAPE_PARAMS]
        return covariance(centred, shape=roi_size, readnoise=readnoise)[:, which][:, :, which]
    cov = fit_covariance(params, errors, correlations, roi_size=roi_size, readnoise=readnoise)
    return cov[:, 1:, 1:]


def joint_z(
    curves_at: Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]],
    z_grid: np.ndarray,
    scatter: np.ndarray,
    p: np.ndarray,
    fitted: np.ndarray,
    cov: np.ndarray,
    *,
    z_only: bool = False,
    on_grid: np.ndarray | None = None,
) -> JointZ:
    """The joint readout (module notes) of spots with fitted (wx, wy, ρ) ``fitted`` (n, 3; or
    (n, planes, 3): the values to compare with each plane of the particle's curves) and
    their covariance ``cov`` (n, 3, 3) on particles ``p`` (n,): ``curves_at(particle, z)`` gives
    the particles' curves (:meth:`~latentz.calibration.result.Calibration.curves_at`),
    ``z_grid`` (particles, planes) their planes (nm) and ``scatter`` (particles, 3) the RMS
    scatter of their wx, wy, ρ about them (NaN: none). With ``z_only``, σ and the spread are
    not computed (NaN). ``on_grid`` (particles, planes, 3): the curves at ``z_grid``, if
    already known."""
    n = len(p)
    out = [np.full(n, np.nan) for _ in range(3)]
    for start in range(0, n, _CHUNK):
        part = slice(start, start + _CHUNK)
        found = _search(curves_at, z_grid, p[part], fitted[part], cov[part] + _diagonal(
            scatter[p[part]]), z_only, on_grid)  # fmt: skip
        for whole, piece in zip(out, found, strict=True):
            whole[part] = piece
    return JointZ(*out)


def _curves(curves_at: Callable, p: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The curves of :data:`SHAPE_PARAMS` at z (p and z broadcast), stacked on a last axis."""
    c = curves_at(p, z)
    return np.stack([c[name] for name in SHAPE_PARAMS], axis=-1)


def _diagonal(scatter: np.ndarray) -> np.ndarray:
    """Covariances (m, 3, 3) of independent errors of 1σ ``scatter`` (m, 3; NaN counts 0)."""
    return np.eye(3) * np.nan_to_num(scatter**2)[:, None, :]


def _weights(total: np.ndarray) -> np.ndarray:
    """Inverse covariances (m, 3, 3); NaN where not finite or not invertible."""
    ok = np.all(np.isfinite(total), axis=(1, 2))
    ok[ok] = np.linalg.det(total[ok]) > 0
    weight = np.full(total.shape, np.nan)
    weight[ok] = np.linalg.inv(total[ok])
    return weight


def _search(curves_at, z_grid, p, fitted, cov, z_only: bool = False,
            on_grid: np.ndarray | None = None) -> tuple[np.ndarray, ...]:  # fmt: skip
    """z, σ and spread of one chunk of spots (:func:`joint_z`), ``cov`` = C_fit + C_curve;
    with ``z_only``, z alone (σ and spread NaN)."""
    grid = z_grid[p]
    weight = _weights(cov)
    by_plane = fitted if fitted.ndim == 3 else fitted[:, None, :]
    d2 = _plane_distances(curves_at, grid, p, by_plane, weight, on_grid)
    rows = np.arange(len(p))
    k = np.argmin(d2, axis=1)
    z = _parabola_vertex(grid, d2, k)
    # d² at z itself: at the best plane, up to half a step off z, it also counts that step
    r = by_plane[rows, k if fitted.ndim == 3 else 0] - _curves(curves_at, p, z)
    best = np.fmin(np.einsum("mi,mij,mj->m", r, weight, r), d2[rows, k])
    found = np.isfinite(best)
    if z_only:
        nothing = np.full(len(p), np.nan)
        return np.where(found, z, np.nan), nothing, nothing
    scale = _held_scale(best)
    step = np.median(np.diff(grid, axis=1), axis=1)
    slope = (_curves(curves_at, p, z + step / 2) - _curves(curves_at, p, z - step / 2)) / step[
        :, None
    ]
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.sqrt(scale / np.einsum("mi,mij,mj->m", slope, weight, slope))
        within = d2 < (best + scale)[:, None]
        spread = np.max(np.where(within, np.abs(grid - z[:, None]), 0.0), axis=1)
    return tuple(np.where(found, v, np.nan) for v in (z, sigma, spread))


def _plane_distances(
    curves_at: Callable, grid: np.ndarray, p: np.ndarray, by_plane: np.ndarray,
    weight: np.ndarray, on_grid: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """d² (m, planes) of fitted values ``by_plane`` (m, 1 or planes, 3) to particles ``p``'
    curves at their planes ``grid`` (m, planes) (or ``on_grid``'s rows of p, the curves
    there), weighted by ``weight`` (m, 3, 3); inf where not finite."""
    curves = _curves(curves_at, p[:, None], grid) if on_grid is None else on_grid[p]
    d2 = _quadratic(by_plane - curves, weight)
    return np.where(np.isfinite(d2), d2, np.inf)


def _quadratic(r: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """rᵀ W r (m, planes) of residuals ``r`` (m, planes, 3) and weights W ``weight`` (m, 3, 3):
    the terms (r_i W_ij) r_j added in turn, i then j (the sums of ``np.einsum("mki,mij,mkj->mk",
    ...)`` to the last bit, a quarter of its time on 10⁵ planes)."""
    parts = [np.ascontiguousarray(r[..., i]) for i in range(3)]
    total = np.zeros(r.shape[:2])
    for i in range(3):
        for j in range(3):
            term = parts[i] * weight[:, i, j, None]
            term *= parts[j]
            total += term
    return total


def _held_scale(best: np.ndarray) -> np.ndarray:
    """The factor on C where the least d² ``best`` says the curves do not hold the spot."""
    return np.where(best > CHI2_HELD, best / 2, 1.0)


def profile_width(
    curves_at: Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]],
    z_grid: np.ndarray,
    scatter: np.ndarray,
    p: np.ndarray,
    fitted: np.ndarray,
    cov: np.ndarray,
    z: np.ndarray,
    window: np.ndarray,
    on_grid: np.ndarray | None = None,
) -> np.ndarray:
    """The 68 % half-width (nm, (n,)) about each spot's ``z`` of its likelihood over the
    planes of its particle that lie in ``window`` ((n, 2), nm: where a spot in range lies).

    Each plane weighs ``exp(−(d² − d²_min) / 2)``, d² the distance of :func:`joint_z` (same
    ``curves_at``, ``z_grid``, ``scatter``, ``p``, ``fitted`` (n, 3), ``cov``, ``on_grid``; C
    scaled by d²_min/2 where the curves do not hold the spot, d²_min the least in the window);
    the width is the |plane − z| that holds :data:`~latentz.calibration.errors.ONE_SIGMA` of the
    weight (:func:`~latentz.calibration.errors.covering_width`). Where the shape hardly changes
    with z, the curvature of d² gives a σ of microns while the spot lies in its window
    whatever its shape: this width is then the window's, weighted by how well each plane fits
    all three of wx, wy, ρ. It resolves nothing finer than the planes' step. NaN where z is
    or no plane in the window has a finite d²."""
    from latentz.calibration.errors import covering_width

    out = np.full(len(p), np.nan)
    for start in range(0, len(p), _CHUNK):
        part = slice(start, start + _CHUNK)
        grid, zz = z_grid[p[part]], z[part]
        weight = _weights(cov[part] + _diagonal(scatter[p[part]]))
        d2 = _plane_distances(curves_at, grid, p[part], fitted[part, None, :], weight, on_grid)
        with np.errstate(invalid="ignore"):
            inside = (grid >= window[part, :1]) & (grid <= window[part, 1:]) & np.isfinite(d2)
        best = np.min(np.where(inside, d2, np.inf), axis=1)
        with np.errstate(invalid="ignore"):
            likelihood = np.where(inside, np.exp(-0.5 * (d2 - best[:, None])
                                                 / _held_scale(best)[:, None]), 0.0)  # fmt: skip
        total = likelihood.sum(axis=1)
        found = np.isfinite(zz) & (total > 0)
        spread = np.abs(grid[found] - zz[found, None])
        share = likelihood[found] / total[found, None]
        out[start + np.flatnonzero(found)] = covering_width(spread, share)
    return out


def _parabola_vertex(grid: np.ndarray, d2: np.ndarray, k: np.ndarray) -> np.ndarray:
    """z of the vertex of the parabola through plane k and its neighbours (m,), kept between
    them; plane k's own z at the grid's ends or where the three are not a minimum."""
    rows = np.arange(len(k))
    lo, hi = np.maximum(k - 1, 0), np.minimum(k + 1, grid.shape[1] - 1)
    z0, z1, z2 = grid[rows, lo], grid[rows, k], grid[rows, hi]
    f0, f1, f2 = d2[rows, lo], d2[rows, k], d2[rows, hi]
    with np.errstate(divide="ignore", invalid="ignore"):
        num = (z1 - z0) ** 2 * (f1 - f2) - (z1 - z2) ** 2 * (f1 - f0)
        den = (z1 - z0) * (f1 - f2) - (z1 - z2) * (f1 - f0)
        vertex = np.clip(z1 - 0.5 * num / den, z0, z2)
    inner = (lo < k) & (hi > k) & np.isfinite(f0 + f1 + f2) & (den < 0)
    return np.where(inner, vertex, z1)

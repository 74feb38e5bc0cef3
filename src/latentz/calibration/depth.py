"""Depth of focus of the calibration spots against their in-focus width: a physical scale for z.

A spot's Gaussian width through focus follows ``σ(z) = σ0 sqrt(1 + ((z − c) / d)²)`` closely
(a Gaussian beam; each axis has its own focus ``c`` under astigmatism). The depth ``d`` is in the
units of the given z, while ``σ0`` is in nm through the pixel size, so ``d / σ0²`` (nm⁻¹) tells a
wrong z step: for a paraxial Gaussian beam it is ``4π n / λ`` (n the immersion index, λ the
wavelength), whatever the numerical aperture, and a z step given k times too large makes it k
times larger (:func:`latentz._shared.sanity.check_z_step`).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

__all__ = ["depth_ratio_per_nm"]

#: Fewest converged planes for a width curve to be fitted.
_MIN_PLANES = 7
#: At most this many particles are fitted (a median needs no more).
_MAX_CURVES = 60


def _fit_curve(z_nm: np.ndarray, width_nm: np.ndarray) -> float:
    """``d / σ0²`` of one width curve (NaN when the fit fails, its focus lies outside the planes
    or it does not describe the widths)."""
    top = int(np.argmin(width_nm))
    span = float(z_nm.max() - z_nm.min())
    start = np.array([width_nm[top], z_nm[top], span / 4])

    def residual(p: np.ndarray) -> np.ndarray:
        return p[0] * np.sqrt(1 + ((z_nm - p[1]) / p[2]) ** 2) - width_nm

    try:
        fit = least_squares(
            residual,
            start,
            bounds=([1e-3, z_nm.min() - span, 1e-3 * span], [np.inf, z_nm.max() + span, 10 * span]),
            loss="soft_l1",
            f_scale=0.05 * float(width_nm[top]),
        )
    except ValueError:
        return np.nan
    sigma0, focus, depth = fit.x
    # a width curve, not noise: its focus among the planes, and the model within a tenth of
    # the widths' range on most planes
    misfit = float(np.median(np.abs(residual(fit.x))))
    fits = z_nm.min() <= focus <= z_nm.max() and misfit <= 0.1 * float(np.ptp(width_nm))
    return float(depth / sigma0**2) if fit.success and fits else np.nan


def depth_ratio_per_nm(z_nm: np.ndarray, widths_nm: np.ndarray) -> float:
    """Median of ``d / σ0²`` (nm⁻¹) over width curves (rows of ``widths_nm``, (n, n_z), nm; NaN
    where a plane did not converge) at planes ``z_nm``. Curves with widths on fewer than half
    the planes are left out; NaN where no curve can be fitted."""
    z = np.asarray(z_nm, dtype=np.float64)
    ratios = []
    for row in np.asarray(widths_nm, dtype=np.float64)[:_MAX_CURVES]:
        ok = np.isfinite(row) & (row > 0)
        if ok.sum() >= max(_MIN_PLANES, z.size // 2):  # a spot on most planes, not noise
            ratios.append(_fit_curve(z[ok], row[ok]))
    ratios = np.asarray(ratios)
    ratios = ratios[np.isfinite(ratios)]
    return float(np.median(ratios)) if ratios.size else np.nan

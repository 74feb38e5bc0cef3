"""Cramér–Rao bounds of a calibrated emitter's x, y and z.

A calibration ties the Gaussian of eq. 1 to z: its widths and ρ follow the calibration curves
(:meth:`~latentz.calibration.Calibration.curves_at`). An emitter of ``N`` photons over a
background ``B`` then has five unknowns, x, y, N, B and z, and its Fisher information is the
Gaussian's (:func:`latentz.fit.fisher_information`, Poisson and read noise) seen through the
Jacobian of (x, y, A, B, wx, wy, ρ) in them, with ``A = N / (2π wx wy sqrt(1 − ρ²))``. No
unbiased estimator that uses the curves does better; latentz fits the seven parameters first and
reads z from the shape, so its errors lie at or above these bounds.
"""

from __future__ import annotations

import numpy as np

from latentz.calibration import Calibration
from latentz.fit import fisher_information

__all__ = ["localization_bounds"]

#: Step of the curves' derivative in z, nm.
_DZ_NM = 10.0


def localization_bounds(
    calibration: Calibration,
    particle: np.ndarray,
    z_nm: np.ndarray,
    photons: np.ndarray,
    background: float,
    *,
    readnoise: float,
) -> np.ndarray:
    """(n, 3) bounds of x and y (px) and z (nm) of emitters at ``z_nm`` near calibration
    ``particle`` (indices), of ``photons`` over ``background`` photoelectrons per pixel, each
    centred in the calibration's ROI; NaN where the curves are not defined."""
    z = np.asarray(z_nm, float)
    at, up, down = (calibration.curves_at(particle, z + dz) for dz in (0.0, _DZ_NM, -_DZ_NM))
    wx, wy, rho = at["wx"], at["wy"], at["rho"]
    slope = {k: (up[k] - down[k]) / (2 * _DZ_NM) for k in ("wx", "wy", "rho")}
    n = np.asarray(photons, float)
    amplitude = n / (2 * np.pi * wx * wy * np.sqrt(1 - rho**2))
    size = calibration.roi_size
    centre = np.full_like(z, (size - 1) / 2)
    params = np.column_stack([centre, centre, amplitude, np.full_like(z, background), wx, wy, rho])
    bounds = np.full((len(z), 3), np.nan)
    ok = np.all(np.isfinite(params), axis=1)
    info = fisher_information(params[ok], shape=size, readnoise=readnoise)
    # d(x, y, A, B, wx, wy, rho) / d(x, y, N, B, z)
    jac = np.zeros((int(ok.sum()), 7, 5))
    jac[:, 0, 0] = jac[:, 1, 1] = jac[:, 3, 3] = 1.0
    jac[:, 2, 2] = amplitude[ok] / n[ok]
    log_slope = -slope["wx"] / wx - slope["wy"] / wy + rho * slope["rho"] / (1 - rho**2)
    jac[:, 2, 4] = (amplitude * log_slope)[ok]
    jac[:, 4, 4], jac[:, 5, 4], jac[:, 6, 4] = slope["wx"][ok], slope["wy"][ok], slope["rho"][ok]
    reduced = np.matmul(np.matmul(jac.transpose(0, 2, 1), info), jac)
    variance = np.diagonal(np.linalg.pinv(reduced), 0, 1, 2)
    bounds[ok] = np.sqrt(variance[:, [0, 1, 4]])
    return bounds

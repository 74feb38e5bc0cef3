"""Cramér–Rao bounds of a calibrated emitter's x, y and z.

A calibration ties the Gaussian of eq. 1 to z: its widths and ρ follow the calibration curves
(:meth:`~latentz.calibration.Calibration.curves_at`). An emitter of ``N`` photons over a
background ``B`` then has five unknowns, x, y, N, B and z, and its Fisher information is the
Gaussian's (:func:`latentz.fit.fisher_information`, Poisson and read noise) seen through the
Jacobian of (x, y, A, B, wx, wy, ρ) in them, with ``A = N / (2π wx wy sqrt(1 − ρ²))``. No
unbiased estimator that uses the curves does better; latentz fits the seven parameters first and
reads z from the shape, so its errors lie at or above these bounds.

Those are the Gaussian's bounds. :func:`psf_bounds` gives the physical ones, from the simulated
microscope's own PSF: what any estimator of a point emitter could reach.

:func:`curves_fit_z` is a yardstick between the Gaussian's bound and latentz: z fitted by maximum
likelihood with the five unknowns, the widths and ρ following the curves (at the spot's
brightness). It is not latentz's readout; it shows how much of the distance to the bound a fit
through the curves would take back, and how much belongs to the Gaussian model itself on a PSF
that is not one.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from latentz.calibration import Calibration
from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.fit import fisher_information, poisson_information, render_rois
from latentz.simulate.molecules import Microscope, molecule_patches

__all__ = ["curves_fit_z", "localization_bounds", "psf_bounds"]

#: Step of the curves' derivative in z, nm.
_DZ_NM = 10.0

#: Steps of :func:`psf_bounds`' central differences in x, y (px) and z (nm).
_DXY_PX, _DZ_PSF_NM = 0.02, 5.0

#: z (nm) at which :func:`curves_fit_z` starts a second search, and its simplex's first steps
#: in x, y (px), ln photons, background (photoelectrons per pixel) and z (nm).
_Z_STARTS_NM = np.arange(-1000.0, 1000.1, 50.0)
_STEPS = np.array([0.3, 0.3, 0.2, 2.0, 50.0])


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


def curves_fit_z(
    calibration: Calibration,
    rois: np.ndarray,
    particle: np.ndarray,
    start: np.ndarray,
) -> np.ndarray:
    """z (nm) of each ROI of ``rois`` ((n, s, s) photoelectrons, s the calibration's ROI) by
    maximum likelihood (Poisson, read noise as a Poisson shift) over x, y, photons, background
    and z, its Gaussian's widths and ρ those of calibration ``particle``'s curves at z
    (:meth:`~latentz.calibration.Calibration.curves_at`) plus the brightness shift of a spot of
    the starting amplitude and background (how much its fit differs from the particle's).
    ``start`` (n, 6): x, y (ROI px), amplitude, background, photons and z (nm) of latentz's fit
    and readout. Of the searches from the start and from the best of :data:`_Z_STARTS_NM`, the
    likelier is kept; NaN where neither is finite."""
    out = np.full(len(rois), np.nan)
    for k, (roi, p, (x, y, amplitude, background, photons, z)) in enumerate(
        zip(rois, particle, start, strict=True)
    ):
        args = (calibration, roi, int(p), {"amplitude": np.array([amplitude]),
                                           "background": np.array([background])})  # fmt: skip
        first = np.array([x, y, np.log(max(photons, 1.0)), max(background, 0.1), z])
        grid = [_curves_nll(np.r_[first[:4], z0], *args) for z0 in _Z_STARTS_NM]
        starts = [first, np.r_[first[:4], _Z_STARTS_NM[int(np.argmin(grid))]]]
        fits = [minimize(_curves_nll, q, args=args, method="Nelder-Mead", options={
            "initial_simplex": np.vstack([q, q + np.diag(_STEPS)]), "xatol": 0.1,
            "fatol": 1e-3, "maxiter": 2000}) for q in starts]  # fmt: skip
        best = min(fits, key=lambda f: f.fun)
        out[k] = best.x[4] if np.isfinite(best.fun) else np.nan
    return out


def _curves_nll(q: np.ndarray, calibration: Calibration, roi: np.ndarray, particle: int,
                brightness: dict[str, np.ndarray]) -> float:  # fmt: skip
    """Negative log-likelihood (up to a constant) of ``roi`` under the Gaussian of
    ``q`` = (x, y, ln photons, background, z) whose shape is :func:`curves_fit_z`'s."""
    at = np.array([particle])
    curves = calibration.curves_at(at, q[4:5])
    shift = shape_params_shift(calibration, brightness, at, q[4:5])
    shape = np.array([curves[c][0] for c in ("wx", "wy", "rho")])
    wx, wy, rho = shape + (0.0 if shift is None else shift[0])
    if not (np.isfinite(wx) and wx > 0 and wy > 0 and abs(rho) < 1 and q[3] > 0):
        return np.inf
    amplitude = np.exp(q[2]) / (2 * np.pi * wx * wy * np.sqrt(1 - rho**2))
    params = np.array([[q[0], q[1], amplitude, q[3], wx, wy, rho]])
    offset = calibration.camera.readnoise**2  # read noise as a Poisson shift
    mu = render_rois(params, shape=calibration.roi_size)[0] + offset
    return float(np.sum(mu - (roi + offset) * np.log(mu)))


def psf_bounds(
    microscope: Microscope,
    x: np.ndarray,
    y: np.ndarray,
    z_nm: np.ndarray,
    photons: np.ndarray,
    background: float,
    *,
    size: int,
) -> np.ndarray:
    """(n, 3) Cramér–Rao bounds of x, y (px) and z (nm) of point emitters at (x, y) (frame
    px) and ``z_nm`` (height above a point's best focus, as
    :func:`~latentz.simulate.molecules.molecule_frames` places them), of ``photons`` over
    ``background`` photoelectrons per pixel, imaged by ``microscope``'s own PSF in a ``size``-px
    window about each, with its camera's read noise (as a Poisson shift). Five unknowns: x, y,
    photons, background and z, the derivatives by central differences (:data:`_DXY_PX`,
    :data:`_DZ_PSF_NM`). Each sub-pixel position is kept two steps inside its pixel, so that the
    window does not move between the differences."""
    col, row = np.floor(x), np.floor(y)
    x = col + np.clip(np.asarray(x, float) - col, 2 * _DXY_PX, 1 - 2 * _DXY_PX)
    y = row + np.clip(np.asarray(y, float) - row, 2 * _DXY_PX, 1 - 2 * _DXY_PX)
    steps = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],
                      [0, 0, -1]]) * np.array([_DXY_PX, _DXY_PX, _DZ_PSF_NM])  # fmt: skip
    at = (np.stack([x, y, np.asarray(z_nm, float)], axis=1)[:, None] + steps).reshape(-1, 3)
    patches, _ = molecule_patches(microscope, at[:, 0], at[:, 1], at[:, 2], size=size)
    patches = patches.reshape(len(x), len(steps), size * size)
    n = np.asarray(photons, float)[:, None]
    slopes = [n * (patches[:, 2 * k + 1] - patches[:, 2 * k + 2]) / (2 * h)
              for k, h in enumerate((_DXY_PX, _DXY_PX, _DZ_PSF_NM))]  # fmt: skip
    # d mu / d (x, y, N, B, z), each pixel
    jac = np.stack([slopes[0], slopes[1], patches[:, 0], np.ones_like(slopes[0]), slopes[2]],
                   axis=2)  # fmt: skip
    info = poisson_information(jac, n * patches[:, 0] + background,
                               readnoise=microscope.camera.readnoise)  # fmt: skip
    return np.sqrt(np.diagonal(np.linalg.inv(info), 0, 1, 2)[:, [0, 1, 4]])

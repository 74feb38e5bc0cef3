"""The fit's part of σ_z, and how far the calibration images say to scale it: a spot's σ of
its shape value through its particle's inverse z(s), and the factor (≤ 1) that the kept
particles' own images, scattering less than their fits say, put on it over z."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from latentz.calibration.errors import fit_sigma_s, measured_noise, noise_by_z, spread_through
from latentz.calibration.spot_columns import ERROR_COLUMNS, PARAMS
from latentz.fit.api import CORRELATION_COLUMNS

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["calibration_scatter", "fit_part_z", "noise_scale", "noise_scale_at",
           "noise_scale_by_z", "through_inverse"]  # fmt: skip


def fit_part_z(cal: CalibrationView, params: np.ndarray, errors: np.ndarray,
               corr: np.ndarray | None, p: np.ndarray, s: np.ndarray,
               ref: np.ndarray) -> np.ndarray:  # fmt: skip
    """The fit's part of z_err (nm) of spots with fitted ``params`` (n, 7), their ``errors``
    and correlations (:func:`~latentz.calibration.errors.fit_sigma_s`) and shape values
    ``s``: σ_s through particle ``p``'s inverse z(s) (:func:`through_inverse`)."""
    sigma_s = fit_sigma_s(cal.shape, params, errors, corr,
                          roi_size=int(cal.options.get("roi_size") or 11),
                          readnoise=cal.camera.readnoise, theta=cal.local.theta,
                          amplitude_ref=ref)  # fmt: skip
    return through_inverse(cal, p, s, sigma_s)


def through_inverse(cal: CalibrationView, p: np.ndarray, s: np.ndarray,
                    sigma_s: np.ndarray) -> np.ndarray:  # fmt: skip
    """1σ (nm) of z of shape values ``s`` with errors ``sigma_s`` on particles ``p``'s
    inverse z(s): its spread over s ± σ_s within the inverse's domain, each z held within
    p's monotonic range, where a spot in range lies
    (:func:`~latentz.calibration.errors.spread_through`; not the slope dz/ds times σ_s,
    which an order-16 inverse's wiggles and steep ends make arbitrary)."""
    model = cal.local.shapes[cal.shape]
    inverse = model.inverse[p]
    return spread_through(inverse, s, sigma_s, inverse.domain, model.z_range[p])


def calibration_scatter(
    cal: CalibrationView,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept particles' calibration images (k, n_z) about their inverse z(s): z (nm),
    residual (nm), the fit's part of ``z_err_nm`` that :meth:`~latentz.calibration.result.
    Calibration.apply` would give each (nm) and the image's leverage in its inverse's fit;
    NaN for images the inverse was not fitted to (outside its monotonic range). Empty without
    fit errors in the traces."""
    if "calibration_scatter" not in cal._cache:
        model, tr, k = cal.local.shapes[cal.shape], cal.traces, cal.kept
        cal._cache["calibration_scatter"] = (np.empty((0, 0)),) * 4
        if all(c in tr.data for c in ERROR_COLUMNS) and k.size:
            n_z = cal.local.z_nm.shape[1]
            params = np.stack([tr[c][k] for c in PARAMS], axis=-1).reshape(-1, 7)
            errors = np.stack([tr[c][k] for c in ERROR_COLUMNS], axis=-1).reshape(-1, 4)
            corr = np.stack([tr.data.get(c, np.full(tr["x"].shape, np.nan))[k]
                             for c in CORRELATION_COLUMNS], axis=-1).reshape(-1, 6)  # fmt: skip
            z, values, span = cal.local.z_nm[k], model.values[k], model.z_range[k]
            fitted = np.isfinite(values) & (z >= span[:, :1]) & (z <= span[:, 1:])
            p = np.repeat(k, n_z)
            s = np.where(fitted, values, 0.0).ravel()
            part = fit_part_z(cal, params, errors, corr, p, s, model.amplitude_ref[p])
            cal._cache["calibration_scatter"] = (
                z,
                model.inverse[k].residuals(values, z),
                np.where(fitted, part.reshape(len(k), n_z), np.nan),
                model.inverse[k].leverage(values, fitted),
            )
    return cal._cache["calibration_scatter"]


def noise_scale(cal: CalibrationView) -> float:
    """:attr:`~latentz.calibration.result.Calibration.noise_scale`: the kept particles'
    usable calibration images against their own fit errors
    (:func:`~latentz.calibration.errors.measured_noise`); 1 for traces without fit errors."""
    if "noise_scale" not in cal._cache:
        z, residual, predicted, leverage = calibration_scatter(cal)
        cal._cache["noise_scale"] = 1.0
        if z.size:
            model, k = cal.local.shapes[cal.shape], cal.kept
            use = np.isfinite(model.sigma_z[k]) & cal.usable_planes[k]
            cal._cache["noise_scale"] = measured_noise(
                residual, np.where(use, predicted, np.nan),
                n_params=model.inverse.order + 1, n_fitted=np.isfinite(leverage).sum(axis=1),
            )  # fmt: skip
    return cal._cache["noise_scale"]


def noise_scale_by_z(cal: CalibrationView) -> tuple[np.ndarray, np.ndarray]:
    """:attr:`~latentz.calibration.result.Calibration.noise_scale_by_z`: z (nm, ascending)
    and the factor there, from every image's residual over its fit's part, corrected for its
    leverage (:func:`~latentz.calibration.errors.noise_by_z`); empty where
    :func:`noise_scale` is 1 or the images are too few to follow z."""
    if "noise_scale_by_z" not in cal._cache:
        cal._cache["noise_scale_by_z"] = (np.empty(0), np.empty(0))
        if noise_scale(cal) < 1:
            z, residual, predicted, leverage = calibration_scatter(cal)
            with np.errstate(invalid="ignore", divide="ignore"):
                scatter2 = (residual / predicted) ** 2
            cal._cache["noise_scale_by_z"] = noise_by_z(
                z.ravel(), scatter2.ravel(), (1 - leverage).ravel()
            )
    return cal._cache["noise_scale_by_z"]


def noise_scale_at(cal: CalibrationView, z: np.ndarray) -> np.ndarray:
    """The factor on the fit's part of ``z_err_nm`` at tilt-corrected z (nm):
    :func:`noise_scale_by_z` there (held beyond its ends), or :func:`noise_scale` where that
    is empty."""
    grid, scale = noise_scale_by_z(cal)
    if grid.size == 0:
        return np.full(np.shape(z), noise_scale(cal))
    return np.interp(np.where(np.isfinite(z), z, 0.0), grid, scale)

"""The errors of each calibration particle's local models z(s), Δx'(z), Δy'(z): their residual
σ through focus, the lateral lack of fit that the traces' own fit errors do not explain, and
the models' 1σ at any z."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from latentz.calibration.local import LocalOptions, sliding_rms
from latentz.calibration.particle_curves import bridge_gaps
from latentz.calibration.rows import interp_rows

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["error_model", "lack_of_fit", "model_sigma"]


def error_model(cal: CalibrationView, axis: str) -> tuple[np.ndarray, np.ndarray, Any]:
    """For "z" (the calibration's shape), "x" or "y": each particle's residual σ (n, n_z)
    with gaps bridged by the nearest finite value, its count of finite values (n,), and for
    "z" the derivative of its inverse z(s) (None for "x" and "y"); computed once."""
    key = f"error_model/{axis}"
    if key not in cal._cache:
        slope = None
        if axis == "z":
            shape = cal.local.shapes[cal.shape]
            sigma, slope = shape.sigma_z, shape.inverse.derivative()
        else:
            sigma = cal.local.sigma_dx if axis == "x" else cal.local.sigma_dy
        filled = bridge_gaps(sigma)
        cal._cache[key] = (filled, np.sum(np.isfinite(sigma), axis=1), slope)
    return cal._cache[key]


def lack_of_fit(cal: CalibrationView, axis: str) -> np.ndarray:
    """For "x" or "y": each particle's lack of fit (px, (n, n_z)), the part of its
    residual σ about Δx'(z), Δy'(z) that its traces' own fit errors do not explain:
    ``sqrt(max(σ_res² − σ_fit², 0))``, both as RMS over the local models' sliding window.

    A Gaussian fitted to the real PSF wanders about any smooth curve of z by a few nm near
    focus (the rings move through the ROI), and every emitter's fits wander like the
    particles' do, by another pattern; a polynomial's own error does not hold it. Zero where
    the traces carry no fit errors."""
    key = f"lack_of_fit/{axis}"
    if key not in cal._cache:
        residual = error_model(cal, axis)[0]
        if f"{axis}_err" not in cal.traces.data:
            cal._cache[key] = np.zeros_like(residual)
        else:
            window = float(cal.options.get("sigma_window_nm", LocalOptions().sigma_window_nm))
            fit = sliding_rms(cal.local.z_nm, cal.traces[f"{axis}_err"], window_nm=window,
                              n_params=0)  # fmt: skip
            fit = bridge_gaps(fit)
            lack = np.sqrt(np.maximum(residual**2 - np.nan_to_num(fit) ** 2, 0.0))
            cal._cache[key] = lack
    return cal._cache[key]


def model_sigma(
    cal: CalibrationView, axis: str, p: np.ndarray, z: np.ndarray, at: tuple | None = None
) -> np.ndarray:
    """1σ (px for "x", "y"; nm for "z") of particle ``p``'s local model of ``axis`` at z:
    its residual σ at that z over the square root of its planes per polynomial parameter
    (``at``: :func:`~latentz.calibration.rows.row_weights` of p and z, if known)."""
    sigma, count, _ = error_model(cal, axis)
    if axis == "z":
        order = cal.local.shapes[cal.shape].inverse.order
    else:
        order = (cal.local.dx if axis == "x" else cal.local.dy).order
    return interp_rows(cal.local.z_nm, sigma, p, z, at) * np.sqrt(
        (order + 1) / np.maximum(count[p], 1)
    )

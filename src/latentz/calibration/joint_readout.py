"""The joint readout of z with a calibration: a spot's fitted wx, wy, ρ against its particle's
curves of the three (:func:`~latentz.calibration.readout.joint_z`), weighted by the fit's
covariance and corrected for the spot's brightness, and the shape value of the z it reads."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.calibration.local_errors import error_model
from latentz.calibration.particle_curves import curves_on_planes, usable_scatter
from latentz.calibration.readout import JointZ, joint_z, shape_covariance
from latentz.calibration.spot_columns import ERROR_COLUMNS, PARAMS, stacked
from latentz.fit.api import CORRELATION_COLUMNS

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["joint_readout", "joint_shape", "shape_fit"]


def joint_readout(
    cal: CalibrationView, cols: dict[str, np.ndarray], p: np.ndarray,
    shift: np.ndarray | None = None, *, z_only: bool = False,
) -> JointZ:  # fmt: skip
    """:meth:`~latentz.calibration.result.Calibration.joint_readout`: the joint readout of
    spots of columns ``cols`` on particles ``p``, weighted by the covariance of their fits
    (:func:`shape_fit`), ``shift`` taken off their fitted wx, wy, ρ."""
    fitted, cov = shape_fit(cal, cols)
    if shift is not None:
        fitted = (fitted if shift.ndim == 2 else fitted[:, None]) - shift
    return joint_z(cal.curves_at, cal.local.z_nm, usable_scatter(cal), p, fitted, cov,
                   z_only=z_only, on_grid=curves_on_planes(cal))  # fmt: skip


def shape_fit(cal: CalibrationView, cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The fitted (wx, wy, ρ) (n, 3) of the spots of columns ``cols`` and their covariance
    (n, 3, 3) times :attr:`~latentz.calibration.result.Calibration.noise_scale` squared
    (:func:`~latentz.calibration.readout.shape_covariance`: their ``*_err`` and ``*_corr``
    columns where they carry them)."""
    params = stacked(cols, PARAMS)
    errors = corr = None
    if all(c in cols for c in ERROR_COLUMNS):
        errors, corr = stacked(cols, ERROR_COLUMNS), stacked(cols, CORRELATION_COLUMNS)
    cov = shape_covariance(params, errors, corr, roi_size=cal.roi_size,
                           readnoise=cal.camera.readnoise)  # fmt: skip
    return params[:, 4:7], cal.noise_scale**2 * cov


def joint_shape(cal: CalibrationView, cols: dict, p: np.ndarray) -> tuple[np.ndarray, JointZ]:
    """The joint readout of the spots of columns ``cols`` and the shape value of its z
    (:func:`_shape_at`). Where the calibration has dimmed refits, the readout is repeated
    with the fitted wx, wy, ρ corrected for the spots' background ratio
    (:func:`~latentz.calibration.brightness_shifts.shape_params_shift`) at the first
    readout's z."""
    joint = joint_readout(cal, cols, p)
    shift = shape_params_shift(cal, cols, p, joint.z_nm)
    if shift is not None:
        joint = joint_readout(cal, cols, p, shift)
    return _shape_at(cal, p, joint.z_nm), joint


def _shape_at(cal: CalibrationView, p: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The shape value whose inverse z(s) of particle ``p`` gives ``z`` (nm): Newton steps
    on z(s) from the forward model s(z); NaN where z is outside the inverse's range."""
    model = cal.local.shapes[cal.shape]
    inverse, slope = model.inverse[p], error_model(cal, "z")[2][p]
    target = np.where(np.isfinite(z), z, 0.0)
    s = model.forward[p](target)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for _ in range(4):
            s = s - (inverse(s) - target) / slope(s)
        hit = np.abs(inverse(s) - target) < 0.5
    return np.where(np.isfinite(z) & hit & inverse.contains(s) & inverse.valid, s, np.nan)

"""What the ``x_err_nm``, ``y_err_nm`` and ``z_err_nm`` of the spots that
:meth:`~latentz.calibration.result.Calibration.apply` places are made of: the spot's own fit,
its particle's local models, the field's part and, laterally, the particles' own reference
(:mod:`latentz.calibration.errors` describes the model)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.calibration.errors import ONE_SIGMA, combine, spread_through
from latentz.calibration.field_errors import field_sigma, z_field_error
from latentz.calibration.joint_readout import shape_fit
from latentz.calibration.local_errors import error_model, lack_of_fit, model_sigma
from latentz.calibration.noise_scale import fit_part_z, noise_scale_at, through_inverse
from latentz.calibration.particle_curves import curves_on_planes, usable_scatter
from latentz.calibration.placing import Placed
from latentz.calibration.readout import JointZ, profile_width
from latentz.calibration.rows import interp_rows, row_weights
from latentz.calibration.spot_columns import ERROR_COLUMNS, PARAMS, stacked
from latentz.fit.api import CORRELATION_COLUMNS

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["spot_errors"]


def spot_errors(cal: CalibrationView, placed: Placed, z_readout: str, error_parts: bool,
                reference: bool) -> dict[str, np.ndarray]:  # fmt: skip
    """:meth:`~latentz.calibration.result.Calibration.apply`'s columns of the ``placed``
    spots, their places with their errors (nm), in order: x_nm, x_err_nm, y_nm, y_err_nm,
    z_nm, z_err_nm, and with ``error_parts`` z_err_fit_nm and z_err_field_nm; laterally with
    the particles' own reference (``reference``) or without."""
    cols, p, z, in_range = placed.cols, placed.p, placed.z, placed.in_range
    distance = np.hypot(*(np.column_stack([cols["x"], cols["y"]]) - cal.positions[p]).T)
    at = row_weights(cal.local.z_nm, p, z)
    z_err, z_fit = _z_error(cal, cols, placed.s, p, z, in_range, at, placed.ref,
                            placed.ref_scatter, placed.joint)  # fmt: skip
    out = {}
    for axis, place in (("x", placed.x_nm), ("y", placed.y_nm)):
        err = _lateral_error(cal, axis, cols, p, z, in_range, at, z_err, distance)
        if reference:
            err = combine(err, cal.reference_sigma_nm(axis))
        out[f"{axis}_nm"] = place
        out[f"{axis}_err_nm"] = np.where(in_range, err, np.nan)
    out["z_nm"] = z
    z_field = z_field_error(cal, cols, z, distance, z_readout)
    out["z_err_nm"] = np.where(in_range, combine(z_err, z_field), np.nan)
    if error_parts:
        out["z_err_fit_nm"] = np.where(in_range, z_fit, np.nan)
        out["z_err_field_nm"] = np.where(in_range, z_field, np.nan)
    return out


def _z_error(
    cal: CalibrationView,
    cols: dict[str, np.ndarray],
    s: np.ndarray,
    p: np.ndarray,
    z: np.ndarray,
    in_range: np.ndarray,
    at: tuple[np.ndarray, np.ndarray, np.ndarray],
    ref: np.ndarray,
    ref_scatter: float,
    joint: JointZ | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """σ_z (nm) before the field model's part: the spot's own (propagated from its fit
    errors where it carries them, else the calibration's at z) with the particle's model
    error, and the amplitude reference's scatter; and the fit's part alone (NaN where the
    spots carry no fit errors). With the ``joint`` readout, the fit's part is its σ or,
    where larger, its spread over a second minimum; with either readout, at most the
    likelihood's width over the particle's range (:func:`_profile_bound`). ``cols``: the
    spots' columns (:func:`~latentz.calibration.spot_columns.spot_arrays`), NaN for a
    correlation they lack."""
    model_part = model_sigma(cal, "z", p, z, at)
    fit_part = np.full(len(s), np.nan)
    if all(c in cols for c in ERROR_COLUMNS):
        if joint is None:  # scaled about each z (noise_scale_by_z)
            params, errors = stacked(cols, PARAMS), stacked(cols, ERROR_COLUMNS)
            fit_part = noise_scale_at(cal, z) * fit_part_z(
                cal, params, errors, stacked(cols, CORRELATION_COLUMNS), p,
                np.where(in_range, s, 0.0), ref)  # fmt: skip
        else:  # its fit covariance already scaled by noise_scale (joint_readout)
            fit_part = np.fmax(joint.sigma_nm, joint.spread_nm)
        fit_part = _profile_bound(cal, cols, p, np.where(in_range, z, np.nan), fit_part)
        z_err = np.hypot(fit_part, model_part)
    else:
        z_err = interp_rows(cal.local.z_nm, error_model(cal, "z")[0], p, z, at)
    if ref_scatter > 0:  # s ∝ A_ref: an error δ in ln A_ref moves s by s·δ; NaN: unknown
        s_in = np.where(in_range, s, 0.0)
        z_err = combine(z_err, through_inverse(cal, p, s_in, np.abs(s_in) * ref_scatter))
    return z_err, fit_part


def _lateral_error(
    cal: CalibrationView,
    axis: str,
    cols: dict,
    p: np.ndarray,
    z: np.ndarray,
    in_range: np.ndarray,
    at: tuple[np.ndarray, np.ndarray, np.ndarray],
    z_err: np.ndarray,
    distance: np.ndarray,
) -> np.ndarray:
    """σ of the corrected ``axis`` position (nm) of the spots of columns ``cols``: the
    spot's own, the particle's model error and lack of fit, its σ_z before the field's part
    (``z_err``; the field's reaches x, y in the field model's held-out errors) through the
    particle's correction (:func:`~latentz.calibration.errors.spread_through` over the z
    where a spot in range lies, :meth:`~latentz.calibration.result.Calibration.
    in_range_window`: the width that holds 68 % of the normal's weight, not the RMS, which the
    curve's steep ends rule), the field model's
    (:func:`~latentz.calibration.field_errors.field_sigma`); the particles' own reference
    (:meth:`~latentz.calibration.result.Calibration.reference_sigma_nm`) is
    :func:`spot_errors`' to add."""
    px = cal.camera.pixel_size_nm
    model = cal.local.dx if axis == "x" else cal.local.dy
    z_in = np.where(in_range, z, 0.0)
    from_z = spread_through(model[p], z_in, np.where(in_range, z_err, 0.0),
                            cal.in_range_window(p, z_in), covering=True)  # fmt: skip
    model_d = model_sigma(cal, axis, p, z, at)
    if f"{axis}_err" in cols:
        own = cols[f"{axis}_err"]
    else:
        own = interp_rows(cal.local.z_nm, error_model(cal, axis)[0], p, z, at)
    field_d = field_sigma(cal, axis, z, distance)  # nm
    lack = interp_rows(cal.local.z_nm, lack_of_fit(cal, axis), p, z, at)
    return combine(own * px, model_d * px, lack * px, from_z * px, field_d)


def _profile_bound(cal: CalibrationView, cols: dict, p: np.ndarray, z: np.ndarray,
                   sigma: np.ndarray) -> np.ndarray:  # fmt: skip
    """``sigma`` (nm), the fit's part of σ_z of the spots of columns ``cols`` read at z on
    particles ``p``, where z is poorly read capped by the 68 % half-width about z of their
    likelihood over the z where a spot in range lies
    (:func:`~latentz.calibration.readout.profile_width` over
    :meth:`~latentz.calibration.result.Calibration.in_range_window`; wx, wy, ρ corrected for
    the spot's brightness as in :func:`~latentz.calibration.joint_readout.joint_shape`).
    Poorly read: ``sigma`` wider than the range alone says (:func:`_range_width`), as where
    the shape hardly changes with z, and σ from the curvature (or from σ_s through the
    inverse, which piles the normal's tails at the range's ends) spans it many times.
    Elsewhere ``sigma`` stands: there the likelihood of the three widths is narrower than
    their errors about the curves (on a validation microscope, 44 % instead of 56 % of spots
    covered)."""
    found = np.isfinite(z)
    window = cal.in_range_window(np.where(found, p, 0), np.where(found, z, 0.0))
    with np.errstate(invalid="ignore"):
        rows = np.flatnonzero(found & (sigma > _range_width(window)))
    if rows.size == 0:
        return sigma
    part = {k: v[rows] for k, v in cols.items()}
    fitted, cov = shape_fit(cal, part)
    shift = shape_params_shift(cal, part, p[rows], z[rows])
    if shift is not None:
        fitted = fitted - shift
    window = window[rows]
    width = profile_width(cal.curves_at, cal.local.z_nm, usable_scatter(cal), p[rows],
                          fitted, cov, z[rows], window, curves_on_planes(cal))  # fmt: skip
    out = sigma.copy()
    out[rows] = np.fmin(sigma[rows], width)
    return out


def _range_width(window: np.ndarray) -> np.ndarray:
    """What a spot's range ``window`` ((n, 2), nm) alone says of its z: the 68 % half-width
    (nm) of a uniform z over it, about its middle."""
    return ONE_SIGMA * (window[:, 1] - window[:, 0]) / 2

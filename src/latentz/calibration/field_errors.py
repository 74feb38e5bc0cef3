"""The part of a spot's error that varies across the field, as held-out calibration particles
measure it: the field model's cross-validated error (:mod:`latentz.calibration.crossval`), the
error of held-out particles seen as emitters and localized by their neighbours
(:mod:`latentz.calibration.dim_crossval`), and the dimming correction's transfer."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz.calibration.crossval import smoothed_noise
from latentz.calibration.dim_crossval import pair_table, transfer_sigma
from latentz.calibration.dimming import background_ratio
from latentz.calibration.errors import FieldLine, combine, field_line, spread_through
from latentz.calibration.local_errors import model_sigma
from latentz.calibration.noise_scale import calibration_scatter, noise_scale_at

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["field_sigma", "z_field_error"]


def z_field_error(cal: CalibrationView, cols: dict, z: np.ndarray, distance: np.ndarray,
                  readout: str) -> np.ndarray:  # fmt: skip
    """The part of σ_z (nm) that varies across the field, as held-out particles measure
    it: the field model's cross-validated error with the dimming correction's transfer
    (at the spot's background ratio c), or, where larger, the error of held-out particles
    seen as emitters of that c and localized by neighbours as far away as the spot is from
    its particle with the z ``readout`` (:func:`_pair_sigma`). That is ``nearest``'s error
    (with the joint readout, the pairs' alone: the cross-validation and the transfer are
    the shape value's, and the pairs hold both for the joint readout): for another field
    model it counts only beyond the distances its cross-validation held out (above their
    90th percentile), where the model extrapolates; ``cols``: the spots' columns
    (:func:`~latentz.calibration.spot_columns.spot_arrays`)."""
    c_spot = None
    if "background" in cols and "dim0_wx" in cal.traces.data:
        c_spot = background_ratio(cols["background"], cols["amplitude"],
                                  cal.camera.readnoise)  # fmt: skip
    pair = _pair_sigma(cal, z, c_spot, distance, readout)
    if readout == "joint" and cal.field_model == "nearest":
        return pair
    field = field_sigma(cal, "z", z, distance)
    if c_spot is not None:
        field = combine(field, _transfer_sigma(cal, z, c_spot))
    pair = np.fmax(field, pair)
    if cal.field_model == "nearest":
        return pair
    held = cal.crossval_of(cal.field_model)["distance_px"].to_numpy()
    return np.where(distance > np.quantile(held, 0.9), pair, field)


def field_sigma(cal: CalibrationView, axis: str, z: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """The field model's 1σ (nm) on ``axis`` (:func:`~latentz.calibration.errors.
    field_sigma`) at z (nm) ``distance`` px from the particle, less the local models' part of
    the held-out errors and, laterally, the held-out particles' own z noise carried through Δ
    (:func:`_carried_noise`)."""
    kind = cal.field_model
    line = _held_out_line(cal, lambda: cal.crossval_of(kind), kind, axis,
                          f"crossval_line/{kind}/{axis}")  # fmt: skip
    return line.sigma(z, distance)


def _carried_noise(cal: CalibrationView, held_out: pd.DataFrame, axis: str) -> np.ndarray:
    """(rows,) nm: how far the held-out particles' own z noise moves their lateral
    ``axis`` error (:func:`~latentz.calibration.crossval.crossval` reads Δx', Δy' at the
    predicted z): the fit's part of σ_z of each held-out image (as
    :meth:`~latentz.calibration.result.Calibration.apply` gives a spot, less the smoothing
    crossval applies to its shape values) and its local model's σ (the neighbours' inverse,
    alike), through the particle's Δx'(z) or Δy'(z)
    (:func:`~latentz.calibration.errors.spread_through`, the width that covers 68 %, as
    for a spot). A spot's own σ_z stands for it (:mod:`~latentz.calibration.spot_errors`);
    the field's z error is not in it (a particle's height moves its z read and its Δ alike,
    and the read z's Δ holds both)."""
    p = held_out["particle"].to_numpy(int)
    z = held_out["z_nm"].to_numpy(float)
    fit = np.zeros(p.size)
    predicted = calibration_scatter(cal)[2]
    if predicted.size and p.size:
        row = np.clip(np.searchsorted(cal.kept, p), 0, cal.kept.size - 1)
        plane = np.argmin(np.abs(cal.local.z_nm[p] - z[:, None]), axis=1)
        fit = np.where(cal.kept[row] == p, predicted[row, plane], 0.0)
        fit = np.nan_to_num(fit) * noise_scale_at(cal, z) * smoothed_noise(cal, p)
    noise_z = np.hypot(fit, np.nan_to_num(model_sigma(cal, "z", p, z)))
    model = (cal.local.dx if axis == "x" else cal.local.dy)[p]
    window = cal.in_range_window(p, z)
    return cal.camera.pixel_size_nm * spread_through(model, z, noise_z, window,
                                                     covering=True)  # fmt: skip


def _held_out_line(cal: CalibrationView, table: Callable[[], pd.DataFrame], kind: str, axis: str,
                   key: str, local_models: bool = True) -> FieldLine:  # fmt: skip
    """The :class:`~latentz.calibration.errors.FieldLine` of the held-out errors
    ``table()`` with the local models' σ at its rows (``local_models``; False: errors not
    read through the local models, none taken off), made once and cached under ``key``."""
    if key not in cal._cache:
        held_out = table()
        scale = 1.0 if axis == "z" else cal.camera.pixel_size_nm
        rows = held_out["particle"].to_numpy(int)
        model_nm = noise_nm = None
        if local_models:
            model_nm = scale * model_sigma(cal, axis, rows, held_out["z_nm"].to_numpy())
            if axis != "z":
                noise_nm = _carried_noise(cal, held_out, axis)
        cal._cache[key] = field_line(held_out, kind, axis, model_nm=model_nm,
                                     noise_nm=noise_nm)  # fmt: skip
    return cal._cache[key]


def _pair_sigma(cal: CalibrationView, z: np.ndarray, c_spot: np.ndarray | None,
                distance: np.ndarray, readout: str = "shape") -> np.ndarray:  # fmt: skip
    """1σ (nm) of the z error of spots at ``z`` of background ratio ``c_spot`` (None: as
    bright as the calibration) ``distance`` px from the particle that localizes them, from
    held-out particles localized by their nearer and farther neighbours with the z
    ``readout`` of :meth:`~latentz.calibration.result.Calibration.apply`
    (:func:`~latentz.calibration.dim_crossval.pair_table`): at each of its ratios c the
    :func:`~latentz.calibration.errors.field_sigma` line in distance, then linear in log c
    between them."""
    key = f"pair_table/{readout}"
    if key not in cal._cache:  # with its ratios c, which a sort of the whole table finds
        table = pair_table(cal, readout)
        cal._cache[key] = table, np.unique(table["c"].to_numpy())
    table, levels = cal._cache[key]
    if len(table) == 0 or not table["in_range"].any():
        return np.zeros(np.shape(z))
    by_level = np.array([
        _held_out_line(cal, lambda c=c: table[table["c"] == c], "pairs", "z",
                       f"pair_line/{readout}/{c}", readout == "shape").sigma(z, distance)
        for c in levels])  # fmt: skip
    if levels.size == 1 or c_spot is None:
        return by_level[0]
    return _interp_levels(np.log(levels), by_level, c_spot)


def _transfer_sigma(cal: CalibrationView, z: np.ndarray, c_spot: np.ndarray) -> np.ndarray:
    """1σ (nm) of the dimming correction carried from the nearest particle to spots at
    ``z`` of background ratio ``c_spot``, measured on held-out particles
    (:func:`~latentz.calibration.dim_crossval.transfer_sigma`): linear in z between its
    bins and in log c between its levels, held at the ends; 0 where unknown."""
    if "transfer_sigma" not in cal._cache:
        cal._cache["transfer_sigma"] = transfer_sigma(cal)
    centres, log_c, sigma = cal._cache["transfer_sigma"]
    if centres.size == 0:
        return np.zeros(np.shape(z))
    zq = np.where(np.isfinite(z), z, centres[0])
    by_level = np.array([np.interp(zq, centres, row) for row in sigma])  # (levels, spots)
    return _interp_levels(log_c, by_level, c_spot)


def _interp_levels(log_c: np.ndarray, by_level: np.ndarray, c_spot: np.ndarray) -> np.ndarray:
    """Values ``by_level`` (levels, spots) at each spot's ratio ``c_spot``: linear in log c
    between the levels ``log_c`` (ascending), held at the ends; the lowest where c is unknown."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.log(np.asarray(c_spot, dtype=np.float64))
    x = np.clip(np.where(np.isfinite(x), x, log_c[0]), log_c[0], log_c[-1])
    j = np.clip(np.searchsorted(log_c, x), 1, log_c.size - 1)
    t = (x - log_c[j - 1]) / (log_c[j] - log_c[j - 1])
    spots = np.arange(x.size)
    return (1 - t) * by_level[j - 1, spots] + t * by_level[j, spots]

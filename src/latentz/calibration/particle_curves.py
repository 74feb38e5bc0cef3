"""The calibration particles' curves of wx, wy (px) and ρ through focus: their traces smoothed
by a running median, read at any z, and how far the traces scatter about them."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from scipy.ndimage import median_filter

from latentz.calibration.local import row_mean
from latentz.calibration.readout import SHAPE_PARAMS
from latentz.calibration.rows import interp_rows, row_weights

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["bridge_gaps", "curves_at", "curves_on_planes", "usable_scatter"]


def curves_at(cal: CalibrationView, particle: Any, z_nm: Any) -> dict[str, np.ndarray]:
    """The calibration curves wx, wy (px) and ρ of particles ``particle`` at tilt-corrected
    ``z_nm`` (arrays of one shape), from their traces smoothed by a running median of 5
    planes; ``<name>_scatter``: each particle's RMS scatter of the trace about that curve."""
    curves = _smoothed(cal)
    p = np.asarray(particle, dtype=int)
    z = np.asarray(z_nm, dtype=np.float64)
    at = row_weights(cal.local.z_nm, p, z)  # where the three curves are read
    out = {}
    for name in SHAPE_PARAMS:
        out[name] = interp_rows(cal.local.z_nm, curves[name], p, z, at)
        out[f"{name}_scatter"] = curves[f"{name}_scatter"][p]
    return out


def curves_on_planes(cal: CalibrationView) -> np.ndarray:
    """(n, n_z, 3) every particle's curves of :data:`~latentz.calibration.readout.SHAPE_PARAMS`
    (:func:`curves_at`) at its own planes, where the joint readout compares a spot with each;
    computed once."""
    if "curves_on_planes" not in cal._cache:
        grid = cal.local.z_nm
        c = curves_at(cal, np.arange(len(grid))[:, None], grid)
        cal._cache["curves_on_planes"] = np.stack([c[name] for name in SHAPE_PARAMS], axis=-1)
    return cal._cache["curves_on_planes"]


def _smoothed(cal: CalibrationView) -> dict[str, np.ndarray]:
    """Each particle's wx, wy, ρ traces (n, n_z) smoothed by a running median of 5 planes
    (gaps bridged first, :func:`bridge_gaps`) and ``<name>_scatter`` (n,), the RMS of the trace
    about it; computed once."""
    if "curves" not in cal._cache:
        curves = {}
        for name in SHAPE_PARAMS:
            raw = cal.traces[name]
            filled = bridge_gaps(raw)
            smooth = median_filter(filled, size=(1, 5), mode="nearest")
            curves[name] = smooth
            with np.errstate(invalid="ignore"):
                curves[f"{name}_scatter"] = np.sqrt(np.nanmean((raw - smooth) ** 2, axis=1))
        cal._cache["curves"] = curves
    return cal._cache["curves"]


def usable_scatter(cal: CalibrationView) -> np.ndarray:
    """(n, 3) RMS scatter of each particle's wx, wy, ρ traces about its curves
    (:func:`curves_at`) over its usable planes (:attr:`~latentz.calibration.result.
    Calibration.usable_planes`): far from focus the fitted widths of ring images jump by far
    more, where no spot is read."""
    if "usable_scatter" not in cal._cache:
        curves = _smoothed(cal)
        use = cal.usable_planes
        with np.errstate(invalid="ignore"):
            cal._cache["usable_scatter"] = np.column_stack([
                np.sqrt(row_mean(np.where(use, (cal.traces[k] - curves[k]) ** 2, np.nan)))
                for k in SHAPE_PARAMS])  # fmt: skip
    return cal._cache["usable_scatter"]


def bridge_gaps(values: np.ndarray) -> np.ndarray:
    """(n, n_z) ``values`` with each row's NaN planes given the previous finite plane's value
    (leading ones the next's); rows with no finite value stay NaN."""
    return pd.DataFrame(values.T).ffill().bfill().to_numpy().T

"""Errors of crowded spots: the fit's position errors times the Birge ratios of its fits.

In crowded frames a ROI holds light of emitters that were not detected (too dim, too defocused,
or merged with a nearer one) and so not taken out (:mod:`.neighbours`); one Gaussian fitted to
it is biased, and its own errors (the sandwich covariance) do not hold that bias. Two fits say
how far they miss: the fit of eq. 1 to the pixels (Pearson χ² over the pixels seen less the
parameters, 7 or a two-emitter fit's 13) and, with a calibration, the reading of z from the
shape (``consistency_chi2`` of :mod:`.quality` over its 2 degrees of freedom: wx, wy and ρ less
the z read from them). :func:`with_crowding_errors` multiplies ``x_err``, ``y_err`` and, with a
calibration, ``x_err_nm``, ``y_err_nm`` and ``z_err_nm`` by the square root of the product of
the two reduced χ² (each at least 1), the Birge ratio of each fit; for the rows of a two-emitter
fit, by the pixel fit's alone (with the shape's too they cover 76–92 % on simulated molecules).
No parameter is tuned. A row whose ROI overlaps no other detection's (no other fit within
``roi_size`` px in x and in y that is not the same emitter) keeps its errors: nothing else is
near, and the misfit of a lone emitter is its real PSF's, which the sandwich errors hold (a real
bead's χ² at 19,000 photons is 2–8x its degrees of freedom).

Measured against truth in ``benchmarks/bench_crowding.py`` (molecules of 300–10,000 photons at
0.2–2 per µm² on random astigmatic microscopes, each calibrated on its own simulated beads;
docs/single-molecules.md, "Crowded frames").
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentz.detect import roi_windows
from latentz.fit._model import N_PARAMS
from latentz.localization.pairs import crowded

__all__ = ["with_crowding_errors", "crowding_factor", "seen_pixels", "SHAPE_DOF", "ERROR_COLUMNS"]

#: Degrees of freedom of ``consistency_chi2``: wx, wy and ρ less the z read from them.
SHAPE_DOF = 2
#: Columns scaled, where present.
ERROR_COLUMNS = ("x_err", "y_err", "x_err_nm", "y_err_nm", "z_err_nm")


def seen_pixels(
    x: np.ndarray, y: np.ndarray, roi_size: int, frame_shape: tuple[int, int]
) -> np.ndarray:
    """Pixels of each square ROI of ``roi_size`` centred on the pixel of (``x``, ``y``; px; NaN
    as 0) that lie inside frames of ``frame_shape`` (rows, columns): its window of
    :func:`latentz.detect.roi_windows`."""
    rows, cols = (np.nan_to_num(np.rint(v), nan=0.0).astype(np.int64) for v in (y, x))
    window = roi_windows(rows, cols, roi_size, frame_shape)[2]
    return (window[:, 1] - window[:, 0]) * (window[:, 3] - window[:, 2])


def crowding_factor(table: pd.DataFrame, frame_shape: tuple[int, int]) -> np.ndarray:
    """Each row's factor (≥ 1) on its position errors: ``sqrt(max(1, χ²/dof) · max(1,
    consistency_chi2 / SHAPE_DOF))``, a χ² that is not finite counting as 1; 1 where the row's
    ROI overlaps no other detection's."""
    roi_size = int(table.attrs["roi_size"])
    near = crowded(table, roi_size)
    if not near.any():
        return np.ones(len(table))
    x, y = table["x"].to_numpy(float), table["y"].to_numpy(float)
    pixels = seen_pixels(x, y, roi_size, frame_shape)
    paired = table["pair"].to_numpy(np.int64) >= 0 if "pair" in table else np.zeros(len(x), bool)
    dof = pixels - np.where(paired, 2 * N_PARAMS - 1, N_PARAMS)
    shape = table["consistency_chi2"].to_numpy(float) if "consistency_chi2" in table else np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = np.fmax(table["chi2"].to_numpy(float) / dof, 1.0)
        factor = np.sqrt(pixel * np.where(paired, 1.0, np.fmax(shape / SHAPE_DOF, 1.0)))
    return np.where(near, factor, 1.0)


def with_crowding_errors(table: pd.DataFrame, frame_shape: tuple[int, int]) -> pd.DataFrame:
    """``table`` (fits of ROIs of ``table.attrs["roi_size"]`` px in frames of ``frame_shape``,
    after :func:`.quality.assess`) with its position errors times `crowding_factor`; the table
    itself where every factor is 1."""
    if len(table) == 0:
        return table
    factor = crowding_factor(table, frame_shape)
    if np.all(factor == 1.0):
        return table
    out = table.copy()
    for column in ERROR_COLUMNS:
        if column in out:
            out[column] = out[column].to_numpy(float) * factor
    return out

"""Errors of the spots fitted at the frame's edge, in ROIs clipped to the frame.

A ROI that reaches past the frame's edge is fitted on its pixels inside the frame
(:func:`latentz.detect.roi_windows`). Its errors from the fit (the sandwich covariance,
:mod:`latentz.fit.robust`) hold the noise of the pixels it saw. A real PSF, unlike the Gaussian
of eq. 1, is not a truncated Gaussian once cut: the fitted centre and widths move with where the
edge cuts the spot, by more than the noise once a few per cent of the spot lie outside. That
truncation error is added here to the fit's errors of a calibrated movie's spots, so that it
reaches z and the corrected positions through :meth:`~latentz.calibration.Calibration.apply`.
It grows with ``m``, the share of the spot outside the frame (`TRUNCATION`); its constants
were fitted against truth on simulated astigmatic microscopes and checked on others
(``benchmarks/bench_edges.py``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.special import ndtr

from latentz.fit.api import CORRELATED

__all__ = ["TRUNCATION", "outside_share", "with_truncation_errors"]

#: The truncation error of the position across the cut, along it, and of the shape (each width,
#: relative, and ρ): ``(slope, power, width factor)``, the error being ``slope * m ** power``
#: times the width (for ρ: times 1), with ``m`` the share outside the frame of a Gaussian
#: ``width factor`` times the fitted one (a real PSF's wings reach farther than the Gaussian's).
TRUNCATION = {"across": (0.35, 1.0, 1.2), "along": (0.10, 0.75, 1.5), "shape": (0.18, 0.75, 1.5)}


def outside_share(centre: np.ndarray, width: np.ndarray, size: int) -> np.ndarray:
    """Share of a Gaussian profile (centre, width in px) beyond a frame's ``size`` pixels, whose
    pixel centres span 0 … size − 1."""
    return ndtr((-0.5 - centre) / width) + ndtr((centre - (size - 0.5)) / width)


def _terms(rows: pd.DataFrame, frame_shape: tuple[int, int], term: str) -> tuple[np.ndarray, ...]:
    """``slope * m ** power`` of ``term`` (`TRUNCATION`) with m of the x axis, of the y axis and
    of the whole spot."""
    slope, power, factor = TRUNCATION[term]
    height, width = frame_shape
    mx = outside_share(rows["x"].to_numpy(float), factor * rows["wx"].to_numpy(float), width)
    my = outside_share(rows["y"].to_numpy(float), factor * rows["wy"].to_numpy(float), height)
    spot = 1.0 - (1.0 - mx) * (1.0 - my)
    return slope * mx**power, slope * my**power, slope * spot**power


def with_truncation_errors(spots: pd.DataFrame, frame_shape: tuple[int, int]) -> pd.DataFrame:
    """``spots`` (a `localize` table, full-frame pixels) with the truncation error of its
    ``edge`` rows added in quadrature to x_err, y_err, wx_err, wy_err and rho_err, and the
    correlations of the shape's parameters scaled to the larger errors (the added error is
    independent of the noise)."""
    edge = spots["edge"].to_numpy(bool)
    if not edge.any():
        return spots
    rows = spots[edge]
    wx, wy = rows["wx"].to_numpy(float), rows["wy"].to_numpy(float)
    across_x, across_y, _ = _terms(rows, frame_shape, "across")
    along_x, along_y, _ = _terms(rows, frame_shape, "along")
    shape = _terms(rows, frame_shape, "shape")[2]
    extra = {
        "x_err": np.hypot(across_x, along_y) * wx,
        "y_err": np.hypot(across_y, along_x) * wy,
        "wx_err": shape * wx,
        "wy_err": shape * wy,
        "rho_err": shape,
    }
    out = spots.copy()
    old = {name: rows[f"{name}_err"].to_numpy(float) for name in ("amplitude", "wx", "wy", "rho")}
    for column, added in extra.items():
        out.loc[edge, column] = np.hypot(rows[column].to_numpy(float), added)
    new = {name: out.loc[edge, f"{name}_err"].to_numpy(float) for name in old}
    for a, b in CORRELATED:
        column = f"{a}_{b}_corr"
        ratio = old[a] * old[b] / (new[a] * new[b])
        out.loc[edge, column] = rows[column].to_numpy(float) * ratio
    return out

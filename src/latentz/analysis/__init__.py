"""Seeing the result: super-resolution rendering, drift correction and Fourier ring correlation
of localization tables (columns frame, x_nm, y_nm, z_nm and their errors)."""

from latentz.analysis.drift_correction import DRIFT_COLUMNS, correct_drift, drift_figure
from latentz.analysis.rendering import RENDER_SUFFIXES, density_images, render, write_render
from latentz.analysis.resolution import FRC, frc

__all__ = [
    "DRIFT_COLUMNS",
    "FRC",
    "RENDER_SUFFIXES",
    "correct_drift",
    "density_images",
    "drift_figure",
    "frc",
    "render",
    "write_render",
]

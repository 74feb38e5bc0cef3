"""The ROI size from the data: the smallest odd square that holds the most defocused kept spot.

Criterion: a square ROI of ``roi`` pixels centred on a Gaussian spot of width ``w`` (standard
deviation, pixels) reaches ``h = roi / 2`` from the centre each way and holds
``erf(h / (w √2))²`` of its photons. The ROI holds the kept spot of the
largest width ``w_max`` (``wx`` or ``wy``, over the kept particles' planes inside the calibrated
range) when ``h ≥ k w_max`` with ``erf(k / √2)² = PHOTON_FRACTION``, so that at most 5 % of the
widest spot's light falls outside, in its faint tails.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erfinv

__all__ = [
    "PHOTON_FRACTION",
    "HALF_WIDTH_PER_SIGMA",
    "MIN_ROI",
    "roi_for_width",
    "roi_limit",
    "widest_spot_px",
]

#: Fraction of the widest kept spot's photons the ROI must hold.
PHOTON_FRACTION = 0.95
#: k in ``h ≥ k w_max``: ``erf(k / √2)² = PHOTON_FRACTION`` (about 2.24).
HALF_WIDTH_PER_SIGMA = float(math.sqrt(2.0) * erfinv(math.sqrt(PHOTON_FRACTION)))
#: The smallest ROI a 7-parameter Gaussian fit is given (pixels).
MIN_ROI = 7


def roi_limit(image_shape: tuple[int, int]) -> int:
    """Largest odd ROI (pixels) that fits images of ``(rows, columns)`` with one pixel to spare
    on each side, so that a particle need not sit exactly at the centre to be detected."""
    side = int(min(image_shape)) - 2
    return side if side % 2 else side - 1


def roi_for_width(width_px: float) -> int:
    """Smallest odd ROI side (pixels, at least :data:`MIN_ROI`) that reaches
    ``HALF_WIDTH_PER_SIGMA`` spot widths ``width_px`` (pixels) from its centre each way."""
    if not np.isfinite(width_px) or width_px <= 0:
        raise ValueError(f"Expected a finite, positive spot width, got {width_px!r} px.")
    return max(MIN_ROI, 2 * math.ceil(HALF_WIDTH_PER_SIGMA * width_px - 0.5) + 1)


def widest_spot_px(cal) -> float:
    """Largest fitted width (``wx`` or ``wy``, pixels) of the kept particles over their usable
    planes (:attr:`~latentz.calibration.Calibration.usable_planes`); NaN if there is none."""
    kept = cal.kept
    widths = np.fmax(cal.traces["wx"][kept], cal.traces["wy"][kept])
    widths = np.where(cal.usable_planes[kept], widths, np.nan)
    return float(np.nanmax(widths)) if np.isfinite(widths).any() else np.nan

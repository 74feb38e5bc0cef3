"""Emitter detection: band-pass, noise level, local maxima and ROI cutting.

:mod:`~latentz.detect.api` is the NumPy-facing API, :mod:`~latentz.detect._kernels` its numba
kernels and :mod:`~latentz.detect._cuda` the CUDA twin with the same algorithm.
"""

from latentz.detect.api import (
    Detections,
    band_noise,
    band_pass,
    cut_photons,
    cut_rois,
    default_threshold,
    detect,
    detect_arrays,
    edge_noise_gain,
    find_peaks,
    pixel_noise,
    roi_corners,
    roi_windows,
    white_noise_gain,
)

__all__ = [
    "Detections",
    "band_noise",
    "band_pass",
    "cut_photons",
    "cut_rois",
    "default_threshold",
    "detect",
    "detect_arrays",
    "edge_noise_gain",
    "find_peaks",
    "pixel_noise",
    "roi_corners",
    "roi_windows",
    "white_noise_gain",
]

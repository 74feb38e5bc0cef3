"""Emitter detection: band-pass filter, local maxima above a noise threshold, ROI cutting.

Each frame (in photoelectrons) is filtered by a difference of Gaussians, ``G(sigma) - G(5 sigma)``,
which smooths shot noise at the scale of a spot and removes the slowly varying background. The
noise of the filtered frame is estimated robustly, as 1.4826 times its median absolute deviation
from the median, and a local maximum (the largest value within ``min_distance`` pixels) is an
emitter when it exceeds ``threshold`` times that noise.

A square ROI of ``roi_size`` pixels is cut around each maximum. Near the frame's edge the ROI is
shifted inward so that it stays whole, and the detection is flagged ``edge``; the fit then still
sees the whole ROI, but the emitter may be cut off. Two maxima that fall inside each other's ROI are
both flagged ``close_pair``: their fits see each other's light.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.spatial import cKDTree

from latentz._shared.validate import check_array, check_int, check_positive

__all__ = [
    "Detections",
    "band_pass",
    "noise_level",
    "find_peaks",
    "roi_corners",
    "cut_rois",
    "detect_arrays",
    "detect",
]

#: Default detection threshold, in units of the filtered background noise.
DEFAULT_THRESHOLD = 5.0
_MAD_TO_SIGMA = 1.4826


class Detections(NamedTuple):
    """Arrays returned by `detect_arrays`, one entry per detected emitter.

    Attributes
    ----------
    frame, row, col : ndarray of int
        Frame index (within the input) and the pixel of the local maximum.
    snr : ndarray
        Filtered value at the maximum in units of the filtered noise.
    row0, col0 : ndarray of int
        Full-frame pixel of each ROI's first pixel ``[0, 0]``.
    edge, close_pair : ndarray of bool
        ROI shifted inward at the frame's edge; another maximum inside this ROI.
    rois : ndarray (n, roi_size, roi_size)
        The ROIs cut from the frames.
    """

    frame: np.ndarray
    row: np.ndarray
    col: np.ndarray
    snr: np.ndarray
    row0: np.ndarray
    col0: np.ndarray
    edge: np.ndarray
    close_pair: np.ndarray
    rois: np.ndarray


def _wide_gaussian_width(sigma: float) -> int:
    """Width (px) of the three boxes whose convolution has the variance of a Gaussian of
    ``sigma`` px."""
    return max(1, int(round(np.sqrt(4.0 * sigma**2 + 1.0))))


def _wide_gaussian(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of width ``sigma`` (pixels) by three box filters (central limit
    theorem: three boxes of width w have variance 3 (w² - 1) / 12). Its cost does not grow with
    ``sigma``, unlike a direct convolution; the background estimate needs no more precision."""
    width = _wide_gaussian_width(sigma)
    out = image
    for _ in range(3):
        out = ndimage.uniform_filter(out, size=width, mode="nearest")
    return out


def band_pass(frame: Any, *, sigma: float = 1.5) -> np.ndarray:
    """Difference of Gaussians ``G(sigma) - G(5 sigma)`` of a 2D frame (sigma in pixels).

    The wide Gaussian, the local background, is approximated by three box filters.
    """
    image = check_array("frame", frame, ndim=2).astype(np.float64)
    sigma = check_positive("sigma", sigma)
    return ndimage.gaussian_filter(image, sigma, mode="nearest") - _wide_gaussian(
        image, 5.0 * sigma
    )


def noise_level(filtered: np.ndarray) -> float:
    """Robust standard deviation of a filtered frame: 1.4826 x median absolute deviation.

    Frames larger than 256 x 256 use every other pixel in each direction: the estimate needs
    tens of thousands of pixels, not millions, and the median is the costly step.
    """
    values = np.asarray(filtered, dtype=np.float64)
    if values.ndim == 2 and values.size > 256 * 256:
        values = values[::2, ::2]
    values = values.ravel()
    return float(_MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))))


def find_peaks(
    frame: Any, *, threshold: float = DEFAULT_THRESHOLD, sigma: float = 1.5, min_distance: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local maxima of the band-passed frame above ``threshold`` times its noise.

    Parameters
    ----------
    frame : array_like (H, W)
        Photoelectrons.
    threshold : float
        In units of the filtered background noise (see `noise_level`).
    sigma : float
        Smoothing scale of the band-pass, in pixels (about the spot's standard deviation).
    min_distance : int
        A maximum is the largest value within this many pixels (Chebyshev distance).

    Returns
    -------
    rows, cols : ndarray of int
    snr : ndarray
        Filtered value at each maximum divided by the noise.
    """
    threshold = check_positive("threshold", threshold)
    min_distance = check_int("min_distance", min_distance, minimum=1)
    filtered = band_pass(frame, sigma=sigma)
    noise = noise_level(filtered)
    if not noise > 0:
        noise = float(np.std(filtered)) or 1.0
    local_max = ndimage.maximum_filter(filtered, size=2 * min_distance + 1, mode="nearest")
    rows, cols = np.nonzero((filtered == local_max) & (filtered > threshold * noise))
    return rows, cols, filtered[rows, cols] / noise


def _close_pairs(rows: np.ndarray, cols: np.ndarray, half: int) -> np.ndarray:
    flags = np.zeros(len(rows), dtype=bool)
    if len(rows) > 1:
        tree = cKDTree(np.column_stack([rows, cols]))
        pairs = tree.query_pairs(r=half, p=np.inf, output_type="ndarray")
        flags[pairs.ravel()] = True
    return flags


def roi_corners(
    rows: np.ndarray, cols: np.ndarray, roi_size: int, frame_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First pixel ``(row0, col0)`` of the ROIs centred on integer ``(rows, cols)``, shifted
    inward to stay whole inside frames of ``frame_shape``, and whether they were shifted."""
    half = roi_size // 2
    row0 = np.clip(rows - half, 0, frame_shape[0] - roi_size)
    col0 = np.clip(cols - half, 0, frame_shape[1] - roi_size)
    return row0, col0, (row0 != rows - half) | (col0 != cols - half)


def cut_rois(
    stack: np.ndarray, frame: np.ndarray, row0: np.ndarray, col0: np.ndarray, roi_size: int
) -> np.ndarray:
    """ROIs ``(n, roi_size, roi_size)`` (float64) of ``stack (t, H, W)`` at the given corners."""
    offsets = np.arange(roi_size)
    return stack[
        frame[:, None, None],
        row0[:, None, None] + offsets[None, :, None],
        col0[:, None, None] + offsets[None, None, :],
    ].astype(np.float64)


def check_frames(frames: Any, roi_size: Any) -> tuple[np.ndarray, int]:
    """``frames`` as a (t, H, W) array and ``roi_size`` as an odd int that fits in a frame."""
    stack = check_array("frames", frames, ndim=(2, 3), dtype_kind="uif")
    stack = stack[None] if stack.ndim == 2 else stack
    roi_size = check_int("roi_size", roi_size, minimum=3)
    if roi_size % 2 == 0:
        raise ValueError(f"Expected `roi_size` to be odd, got {roi_size}.")
    if roi_size > min(stack.shape[1:]):
        raise ValueError(
            f"Expected `roi_size` ({roi_size}) to fit in the frames of shape {stack.shape[1:]}."
        )
    return stack, roi_size


def detect_arrays(
    frames: Any,
    *,
    roi_size: int = 11,
    threshold: float | None = None,
    sigma: float = 1.5,
    min_distance: int = 2,
) -> Detections:
    """Detect emitters in each frame and cut a ROI around each; the array core of `detect`.

    Parameters
    ----------
    frames : array_like (t, H, W) or (H, W)
        Photoelectrons.
    roi_size : int
        Side of the square ROIs in pixels (odd, >= 3, at most the frame's smaller side).
    threshold : float, optional
        In units of the filtered background noise; default `DEFAULT_THRESHOLD`.
    sigma, min_distance
        As in `find_peaks`.

    Returns
    -------
    Detections
    """
    stack, roi_size = check_frames(frames, roi_size)
    _, height, width = stack.shape
    threshold = DEFAULT_THRESHOLD if threshold is None else threshold
    half = roi_size // 2
    parts = []
    for t, frame in enumerate(stack):
        rows, cols, snr = find_peaks(
            frame, threshold=threshold, sigma=sigma, min_distance=min_distance
        )
        row0, col0, edge = roi_corners(rows, cols, roi_size, (height, width))
        close = _close_pairs(rows, cols, half)
        parts.append((np.full(len(rows), t), rows, cols, snr, row0, col0, edge, close))
    columns = [np.concatenate(c) for c in zip(*parts, strict=True)]
    frame_idx, _, _, _, row0, col0 = (c.astype(np.int64) for c in columns[:6])
    rois = cut_rois(stack, frame_idx, row0, col0, roi_size)
    return Detections(
        frame_idx,
        columns[1].astype(np.int64),
        columns[2].astype(np.int64),
        columns[3].astype(np.float64),
        row0,
        col0,
        columns[6].astype(bool),
        columns[7].astype(bool),
        rois,
    )


def detect(
    frames: Any,
    *,
    roi_size: int = 11,
    threshold: float | None = None,
    sigma: float = 1.5,
    min_distance: int = 2,
) -> pd.DataFrame:
    """Detect emitters; one row per detection with frame, row, col, snr, edge and close_pair.

    See `detect_arrays` for the parameters; the ROIs themselves are not returned here.
    """
    found = detect_arrays(
        frames, roi_size=roi_size, threshold=threshold, sigma=sigma, min_distance=min_distance
    )
    return pd.DataFrame(
        {
            "frame": found.frame,
            "row": found.row,
            "col": found.col,
            "snr": found.snr,
            "edge": found.edge,
            "close_pair": found.close_pair,
        }
    )

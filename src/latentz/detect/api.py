"""Emitter detection: band-pass filter, local maxima above a noise threshold, ROI cutting.

Each frame (in photoelectrons) is filtered by a difference of Gaussians, ``G(sigma) - G(5 sigma)``,
which smooths shot noise at the scale of a spot and removes the slowly varying background. The
noise of the filtered frame is the noise of the frame's pixels, estimated from differences of
neighbouring pixels that the spots hardly touch (`pixel_noise`), times the filter's gain on
white noise (`white_noise_gain`). A local maximum (the largest value within ``min_distance``
pixels) is an emitter when it exceeds ``threshold`` times that noise, raised near the frame's
edges where the filter's padding raises the noise (`edge_noise_gain`).

A square ROI of ``roi_size`` pixels is cut around each maximum. Near the frame's edge the ROI is
shifted inward so that it stays whole, and the detection is flagged ``edge``. `latentz.localize`
then fits such an emitter in the ROI centred on it, clipped to the frame (`roi_windows`). Two
maxima that fall inside each other's ROI are both flagged ``close_pair``: their fits see each
other's light.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numba
import numpy as np
import pandas as pd
from scipy import ndimage

from latentz._shared.medians import row_medians_and_mads
from latentz._shared.threads import one_thread_if
from latentz._shared.validate import check_array, check_int, check_positive
from latentz.camera import Camera
from latentz.detect import _kernels as _k

__all__ = [
    "Detections",
    "band_pass",
    "pixel_noise",
    "white_noise_gain",
    "band_noise",
    "edge_noise_gain",
    "find_peaks",
    "roi_corners",
    "roi_windows",
    "cut_rois",
    "cut_photons",
    "merge_maxima",
    "detect_arrays",
    "detect",
]

#: Default detection threshold on frames of `_REFERENCE_AREA` pixels, in units of the filtered
#: background noise; larger frames get a higher default (`default_threshold`).
DEFAULT_THRESHOLD = 5.0
_REFERENCE_AREA = 256 * 256
_MAD_TO_SIGMA = 1.4826
#: A maximum within this many sigma of a higher one, with no dip of `_MERGE_DIP` noise units
#: between them, is a noise ripple on the same spot, not a second emitter.
_MERGE_RADIUS_SIGMAS = 3.0
_MERGE_DIP = 2.0
#: Pixels per maximum that the kernels' output has room for at first.
_PIXELS_PER_MAXIMUM = 32 * 32
#: Chunks of fewer pixels are detected on one thread (`one_thread_if`).
_SMALL_PIXELS = 2**20


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


class FilterPlan(NamedTuple):
    """The band-pass of `band_pass`, for a spot scale ``sigma`` (px).

    ``weights``: the small Gaussian G(sigma), 2 r + 1 taps with r = ceil(3 sigma), normalised.
    ``factor``: side of the blocks whose means make the shrunk frame for the wide Gaussian.
    ``wide_weights``: the wide Gaussian on the shrunk frame, in block units, such that with the
    blocks' own spread it is G(5 sigma) in frame pixels.
    """

    weights: np.ndarray
    factor: int
    wide_weights: np.ndarray


def _gaussian_taps(sd: float) -> np.ndarray:
    radius = max(1, math.ceil(3.0 * sd))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sd) ** 2)
    return taps / taps.sum()


def filter_plan(sigma: float) -> FilterPlan:
    """The filter of `band_pass` for spots of standard deviation ``sigma`` px."""
    wide = 5.0 * sigma
    factor = max(1, int(round(wide / 2.0)))
    # a block mean is a box of `factor` px, variance (factor^2 - 1) / 12
    wide_sd = math.sqrt(max(wide**2 - (factor**2 - 1) / 12.0, 0.25)) / factor
    return FilterPlan(_gaussian_taps(sigma), factor, _gaussian_taps(wide_sd))


def _block_means(image: np.ndarray, factor: int) -> np.ndarray:
    h, w = image.shape
    hs, ws = -(-h // factor), -(-w // factor)
    padded = np.full((hs * factor, ws * factor), np.nan)
    padded[:h, :w] = image
    return np.nanmean(padded.reshape(hs, factor, ws, factor), axis=(1, 3))


def _bilinear_axis(n: int, factor: int, n_small: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pos = np.clip((np.arange(n) + 0.5) / factor - 0.5, 0.0, n_small - 1.0)
    i0 = np.floor(pos).astype(int)
    return i0, np.minimum(i0 + 1, n_small - 1), pos - i0


def band_pass(frame: Any, *, sigma: float = 1.5) -> np.ndarray:
    """Band-passed 2D frame (float64): the small Gaussian ``G(sigma)`` minus the local background
    ``G(5 sigma)``, both with nearest-edge padding (sigma in pixels).

    The background is smooth, so it is blurred on a frame shrunk by block means
    (`filter_plan`) and read back by bilinear interpolation. This NumPy function is the reference
    twin of the numba kernels that `detect_arrays` runs.
    """
    image = check_array("frame", frame, ndim=2).astype(np.float64)
    plan = filter_plan(check_positive("sigma", sigma))
    small = image
    for axis in (0, 1):
        small = ndimage.correlate1d(small, plan.weights, axis, mode="nearest")
    shrunk = _block_means(image, plan.factor)
    for axis in (0, 1):
        shrunk = ndimage.correlate1d(shrunk, plan.wide_weights, axis, mode="nearest")
    return small - _upsampled(shrunk, image.shape, plan.factor)


def _upsampled(shrunk: np.ndarray, shape: tuple[int, int], factor: int) -> np.ndarray:
    """Values on the grid of ``factor`` px blocks read bilinearly at each pixel of ``shape``."""
    r0, r1, fy = _bilinear_axis(shape[0], factor, shrunk.shape[0])
    c0, c1, fx = _bilinear_axis(shape[1], factor, shrunk.shape[1])
    top = shrunk[r0][:, c0] + fx * (shrunk[r0][:, c1] - shrunk[r0][:, c0])
    bottom = shrunk[r1][:, c0] + fx * (shrunk[r1][:, c1] - shrunk[r1][:, c0])
    return top + fy[:, None] * (bottom - top)


def noise_stride(shape: tuple[int, ...]) -> int:
    """Pixel stride (both axes) of the sample `pixel_noise` uses: about 65 000 pixels at least."""
    return max(1, int(math.sqrt(shape[-2] * shape[-1] / 65536)))


def pixel_noise(frames: Any, *, camera: Camera | None = None) -> np.ndarray:
    """Noise of each frame's pixels (t,), photoelectrons, robust to the emitters in it.

    The standard deviation, clipped at 3 sd (`_clipped_spread`), of each pixel's difference from
    the mean of its eight neighbours, over sqrt(9 / 8), at every `noise_stride`-th pixel both
    ways (tens of thousands of pixels: a sampling error near 0.5 %). A smooth background
    cancels, and an emitter touches only the few differences that reach its core, so a frame
    crowded with spots reads near its background's noise (among 250 bright spots per 256 x 256 px
    frame 1.14x, where the spread of the band-passed frame itself, which the spots widen, reads
    5.4x: tests/test_detect.py). Row and column patterns count as pixel noise. ``frames``
    (t, H, W) or (H, W) are photoelectrons, or ADU with ``camera``.
    """
    stack = check_array("frames", frames, ndim=(2, 3), dtype_kind="uif")
    stack = stack[None] if stack.ndim == 2 else stack
    height, width = stack.shape[1:]
    if min(height, width) < 3:
        raise ValueError(f"Expected frames of at least 3 x 3 px, got {height} x {width}.")
    step = noise_stride(stack.shape)
    offset, gain, scale = _camera_terms((height, width), camera)
    diffs = np.empty((len(stack), -(-(height - 2) // step), -(-(width - 2) // step)), np.float32)
    _k.neighbour_differences(np.ascontiguousarray(stack), offset, gain, scale, step, diffs)
    return _clipped_spread(diffs.reshape(len(stack), -1)) / math.sqrt(1.125)


#: `_clipped_spread` keeps the values within this many standard deviations of the mean ...
_CLIP_SDS = 3.0
#: ... whose variance is this fraction of a normal distribution's.
_CLIPPED_VARIANCE = 0.97334


def _clipped_spread(values: np.ndarray, *, rounds: int = 5) -> np.ndarray:
    """Standard deviation of each row of ``values`` (t, n) without its outliers: from 1.4826 x
    the median absolute deviation, ``rounds`` times the standard deviation of the values within
    `_CLIP_SDS` of their mean, corrected for the clipped tails of a normal distribution
    (`_kernels.clipped_spreads`). Unlike a median it does not step with integer counts. 0 for a
    row without spread."""
    centre, spread = row_medians_and_mads(values)
    out = _MAD_TO_SIGMA * spread.astype(np.float64)
    _k.clipped_spreads(np.ascontiguousarray(values, np.float32), centre.astype(np.float64),
                       out, _CLIP_SDS, _CLIPPED_VARIANCE, rounds)  # fmt: skip
    return out


@functools.lru_cache(maxsize=32)
def white_noise_gain(sigma: float) -> float:
    """Standard deviation of `band_pass` (spot scale ``sigma`` px) on white noise of standard
    deviation 1, away from the frame's edges: the root sum of squares of its response to one
    bright pixel, averaged over that pixel's places in the wide background's blocks."""
    plan = filter_plan(check_positive("sigma", sigma))
    half = 5 * math.ceil(5.0 * sigma) + 3 * plan.factor
    squares = []
    for dr, dc in itertools.product(range(plan.factor), repeat=2):
        pixel = np.zeros((2 * half + plan.factor, 2 * half + plan.factor))
        pixel[half + dr, half + dc] = 1.0
        squares.append(np.sum(band_pass(pixel, sigma=sigma) ** 2))
    return float(np.sqrt(np.mean(squares)))


def edge_noise_gain(n: int, weights: np.ndarray) -> np.ndarray:
    """Noise of a line of ``n`` pixels filtered with ``weights`` (nearest-edge mode) relative to
    its interior, per pixel, for white noise.

    Near an edge the taps that fall outside the line all weigh the edge pixel, so its noise
    counts more: 1.56x on the edge pixel for sigma = 1.5 px. The noise of the band-passed frame
    at pixel ``(i, j)`` is `band_noise` times the row gain at ``i`` times the column gain at
    ``j`` (the wide background's share of the noise is neglected), and maxima must clear the
    threshold in those units: a fixed threshold finds most false maxima along the edges.
    """
    r = (len(weights) - 1) // 2
    if n == 1:  # every tap weighs the one pixel
        return np.full(1, np.sum(weights) / math.sqrt(np.sum(weights**2)))
    gain = np.ones(n)
    near = np.unique(np.r_[np.arange(min(r, n)), np.arange(max(n - r, 0), n)])
    taps = near[:, None] + np.arange(-r, r + 1)
    low, high = taps <= 0, taps >= n - 1  # taps that weigh the first and the last pixel
    inside = ~(low | high)
    squares = (low * weights).sum(axis=1) ** 2 + (high * weights).sum(axis=1) ** 2
    squares += (inside * weights**2).sum(axis=1)
    gain[near] = np.sqrt(squares / np.sum(weights**2))
    return gain


def default_threshold(height: int, width: int) -> float:
    """Threshold (noise units) with as many false maxima per frame as `DEFAULT_THRESHOLD` gives
    on 256 x 256 px: the false maxima of smooth Gaussian noise above ``u`` scale as
    ``area u^2 exp(-u^2 / 2)``, so a fixed 5 would find about 60x more on 2048 x 2048 frames
    (about 5 per frame). Frames of 256 x 256 px or less keep 5."""
    area = max(height * width, _REFERENCE_AREA)
    target = 0.5 * DEFAULT_THRESHOLD**2 - math.log(DEFAULT_THRESHOLD**2)
    target += math.log(area / _REFERENCE_AREA)
    u = DEFAULT_THRESHOLD
    for _ in range(50):  # Newton on f(u) = u^2 / 2 - 2 log u - target, increasing for u > 2
        u -= (0.5 * u * u - 2.0 * math.log(u) - target) / (u - 2.0 / u)
    return u


def find_peaks(
    frame: Any, *, threshold: float | None = None, sigma: float = 1.5, min_distance: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local maxima of the band-passed frame above ``threshold`` times its noise (NumPy).

    The reference twin of the kernels' maxima (before `detect_arrays` merges the maxima of one
    wide spot).

    Parameters
    ----------
    frame : array_like (H, W)
        Photoelectrons.
    threshold : float, optional
        In units of the filtered background noise (see `band_noise`); default
        `default_threshold` of the frame's size.
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
    image = check_array("frame", frame, ndim=2)
    if threshold is None:
        threshold = default_threshold(*image.shape)
    threshold = check_positive("threshold", threshold)
    min_distance = check_int("min_distance", min_distance, minimum=1)
    filtered = band_pass(image, sigma=sigma)
    noise = float(band_noise(image, sigma=sigma)[0])
    weights = filter_plan(sigma).weights
    local_noise = noise * np.outer(
        edge_noise_gain(image.shape[0], weights), edge_noise_gain(image.shape[1], weights)
    )
    local_max = ndimage.maximum_filter(filtered, size=2 * min_distance + 1, mode="nearest")
    rows, cols = np.nonzero((filtered == local_max) & (filtered > threshold * local_noise))
    return rows, cols, filtered[rows, cols] / noise


def _usable_noise(noise: Any) -> Any:
    """A zero noise level (a blank or noise-free frame) becomes 1 photoelectron."""
    return np.where(np.asarray(noise) > 0, noise, 1.0)


def roi_corners(
    rows: np.ndarray, cols: np.ndarray, roi_size: int, frame_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First pixel ``(row0, col0)`` of the ROIs centred on integer ``(rows, cols)``, shifted
    inward to stay whole inside frames of ``frame_shape``, and whether they were shifted."""
    half = roi_size // 2
    row0 = np.clip(rows - half, 0, frame_shape[0] - roi_size)
    col0 = np.clip(cols - half, 0, frame_shape[1] - roi_size)
    return row0, col0, (row0 != rows - half) | (col0 != cols - half)


def roi_windows(
    rows: np.ndarray, cols: np.ndarray, roi_size: int, frame_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """ROIs centred on integer ``(rows, cols)``, moved into frames of ``frame_shape`` where the
    centre lies outside: first pixels ``(row0, col0)`` (negative, or beyond the frame's last
    ``roi_size`` pixels, where the ROI reaches past the frame's edge), the window of each
    ROI that lies inside the frame (``(row_start, row_stop, col_start, col_stop)``, ROI pixels,
    :mod:`latentz.fit.windows`), and whether it is clipped."""
    height, width = frame_shape
    half = roi_size // 2
    row0 = np.clip(rows, 0, height - 1) - half
    col0 = np.clip(cols, 0, width - 1) - half
    windows = np.column_stack(
        [
            np.maximum(-row0, 0),
            np.minimum(height - row0, roi_size),
            np.maximum(-col0, 0),
            np.minimum(width - col0, roi_size),
        ]
    ).astype(np.int64)
    clipped = np.any(windows != [0, roi_size, 0, roi_size], axis=1)
    return row0, col0, windows, clipped


def cut_rois(
    stack: np.ndarray, frame: np.ndarray, row0: np.ndarray, col0: np.ndarray, roi_size: int
) -> np.ndarray:
    """ROIs ``(n, roi_size, roi_size)`` (float64) of ``stack (t, H, W)`` at the given corners;
    the pixels of a ROI that lie outside the frame are NaN. Copied pixel by pixel in numba
    (`_kernels.cut_rois`): NumPy's gather through broadcast index arrays took 9 ms for 4000
    ROIs of 11 x 11 px."""
    rois = np.empty((len(frame), roi_size, roi_size))
    index = (np.asarray(a, np.int64) for a in (frame, row0, col0))
    _k.cut_rois(np.asarray(stack), *index, rois)
    return rois


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


def check_noise(noise: Any, n_frames: int) -> np.ndarray | None:
    """``noise`` of `detect_arrays` as float64 (None stays None): one value > 0 per frame."""
    if noise is None:
        return None
    values = check_array("noise", noise, ndim=1, dtype_kind="f").astype(np.float64)
    if len(values) != n_frames or not np.all(values > 0):
        raise ValueError(f"Expected `noise` to hold {n_frames} values > 0, got {values}.")
    return values


def cut_photons(
    stack: np.ndarray,
    frame: np.ndarray,
    row0: np.ndarray,
    col0: np.ndarray,
    roi_size: int,
    camera: Camera | None = None,
) -> np.ndarray:
    """`cut_rois` of frames as stored (ADU when ``camera`` is given), in photoelectrons
    (float64): ``(adu - offset) * gain / flatfield`` at each ROI's own pixels."""
    rois = cut_rois(stack, frame, row0, col0, roi_size)
    if camera is None:
        return rois
    photons = (rois - camera.offset) * camera.gain
    if camera.flatfield is not None:
        zero = np.zeros(len(row0), np.int64)
        photons /= cut_rois(camera.flatfield[None], zero, row0, col0, roi_size)
    return photons


def detect_arrays(
    frames: Any,
    *,
    roi_size: int = 11,
    threshold: float | None = None,
    sigma: float = 1.5,
    min_distance: int = 2,
    noise: Any = None,
    camera: Camera | None = None,
) -> Detections:
    """Detect emitters in each frame and cut a ROI around each; the array core of `detect`.

    Parameters
    ----------
    frames : array_like (t, H, W) or (H, W)
        Photoelectrons, or ADU (any integer or float type, uint16 from a camera) when ``camera``
        is given: each pixel is converted where the kernels read it, no photoelectron copy of the
        frames is made.
    roi_size : int
        Side of the square ROIs in pixels (odd, >= 3, at most the frame's smaller side).
    threshold : float, optional
        In units of the filtered background noise; default `default_threshold` of the frame
        size (5 up to 256 x 256 px, about 5.8 at 2048 x 2048 px).
    sigma, min_distance
        As in `find_peaks`.
    noise : array_like (t,), optional
        Noise of each band-passed frame in photoelectrons, when known (`band_noise`, for
        frames of the same movie); default: estimated on each frame.
    camera : Camera, optional
        Offset (ADU), gain (photoelectrons per ADU) and flatfield of ADU frames.

    Returns
    -------
    Detections
        ROIs in photoelectrons (float64).
    """
    stack, roi_size = check_frames(frames, roi_size)
    n_frames, height, width = stack.shape
    noise = check_noise(noise, n_frames)
    if threshold is None:
        threshold = default_threshold(height, width)
    threshold = check_positive("threshold", threshold)
    sigma = check_positive("sigma", sigma)
    min_distance = check_int("min_distance", min_distance, minimum=1)
    with one_thread_if(stack.size < _SMALL_PIXELS):
        chunk, noise, maxima = _streamed(stack, sigma, camera, threshold, min_distance, noise)
        frame, rows, cols, snr, close = _merged(chunk, noise, maxima, roi_size // 2)
    row0, col0, edge = roi_corners(rows, cols, roi_size, (height, width))
    rois = cut_photons(chunk.frames, frame, row0, col0, roi_size, camera)
    return Detections(frame, rows, cols, snr, row0, col0, edge, close, rois)


class _Chunk(NamedTuple):
    """Frames as stored, their camera terms and wide background: the arguments with which
    `_kernels.valleys_in_frames` recomputes the band-pass at a few pixels."""

    frames: np.ndarray
    offset: np.float32
    gain: np.float32
    scale: np.ndarray  # gain / flatfield (H, W) float32, or (0, 0) for a uniform camera
    background: np.ndarray  # (t, hs, ws) float32
    factor: int
    weights: np.ndarray  # float32
    sigma: float

    @property
    def args(self) -> tuple:
        return (self.frames, self.offset, self.gain, self.scale, self.background, self.factor,
                self.weights)  # fmt: skip


class _Maxima(NamedTuple):
    """Local maxima of a chunk's band-passed frames (each frame's in row order)."""

    frame: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray  # float64, photoelectrons


def _camera_terms(shape: tuple[int, int], camera: Camera | None) -> tuple:
    """(offset, gain, scale) of `_Chunk` for frames of ``shape`` from ``camera``."""
    if camera is None:
        return np.float32(0.0), np.float32(1.0), np.empty((0, 0), np.float32)
    flat = camera.flatfield_region(shape)
    scale = np.empty((0, 0), np.float32) if flat is None else (camera.gain / flat)
    return np.float32(camera.offset), np.float32(camera.gain), scale.astype(np.float32)


def _strips(n_frames: int, height: int) -> int:
    """Row strips per frame: enough (frame, strip) tasks for every thread, strips >= 64 rows."""
    want = -(-4 * numba.get_num_threads() // n_frames)
    return max(1, min(want, height // 64))


def band_noise(frames: Any, *, sigma: float = 1.5, camera: Camera | None = None) -> np.ndarray:
    """Noise of each band-passed frame (t, H, W) in photoelectrons, as `detect_arrays`
    estimates it: the `pixel_noise` times the band-pass's `white_noise_gain` (a blank frame's
    counts as 1 photoelectron). Pass it back there to detect later frames of the same movie, or
    parts of them, with the same noise."""
    stack, _ = check_frames(frames, 3)
    sigma = check_positive("sigma", sigma)
    return _usable_noise(pixel_noise(stack, camera=camera) * white_noise_gain(sigma))


def _streamed(
    stack: np.ndarray,
    sigma: float,
    camera: Camera | None,
    threshold: float,
    min_distance: int,
    noise: np.ndarray | None,
) -> tuple[_Chunk, np.ndarray, _Maxima]:
    """The chunk, the noise of each frame (photoelectrons; `band_noise` unless given) and the
    local maxima above ``threshold`` times it, from one streaming pass
    (`_kernels.detect_frames`)."""
    stack = np.ascontiguousarray(stack)
    n, height, width = stack.shape
    plan = filter_plan(sigma)
    small = (-(-height // plan.factor), -(-width // plan.factor))
    chunk = _Chunk(stack, *_camera_terms((height, width), camera),
                   np.empty((n, *small), np.float32), plan.factor,
                   plan.weights.astype(np.float32), sigma)  # fmt: skip
    if noise is None:
        noise = band_noise(stack, sigma=sigma, camera=camera)
    return chunk, noise, _pass(chunk, (threshold * noise).astype(np.float32), min_distance)


def _pass(chunk: _Chunk, limits: np.ndarray, min_distance: int) -> _Maxima:
    """`_kernels.detect_frames` over the chunk: the maxima above ``limits`` (photoelectrons, one
    per frame) times the edge gains. Fills ``chunk.background``."""
    n, height, width = chunk.frames.shape
    strips = _strips(n, height)
    gain_rows, gain_cols = _edge_gains((height, width), chunk.sigma)
    plan = filter_plan(chunk.sigma)
    wide = plan.wide_weights.astype(np.float32)
    counts = np.zeros(n * strips, np.int64)
    # room for a maximum per 32 x 32 px (a fuller task is rerun with room for its count)
    cap = max(256, height * width // (strips * _PIXELS_PER_MAXIMUM))
    while True:
        rows = np.empty((n * strips, cap), np.int64)
        cols = np.empty((n * strips, cap), np.int64)
        values = np.empty((n * strips, cap), np.float32)
        # threads take the tasks one at a time: one slowed by other work (the fits of the chunk
        # before, in another thread) holds up no other
        with numba.parallel_chunksize(1):
            _k.detect_frames(
                chunk.frames, chunk.offset, chunk.gain, chunk.scale, chunk.factor, chunk.weights,
                tuple(chunk.weights), wide, limits, gain_rows, gain_cols, min_distance, strips,
                rows, cols, values, counts, chunk.background,
            )  # fmt: skip
        if counts.max(initial=0) <= cap:
            break
        cap = int(counts.max())
    taken = np.arange(cap)[None, :] < counts[:, None]
    frame = np.repeat(np.arange(n * strips) // strips, counts)
    return _Maxima(frame, rows[taken], cols[taken], values[taken].astype(np.float64))


def _edge_gains(shape: tuple[int, int], sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """`edge_noise_gain` of the rows and of the columns of frames of ``shape`` (float32)."""
    weights = filter_plan(sigma).weights
    return tuple(edge_noise_gain(n, weights).astype(np.float32) for n in shape)


def _merged(chunk: _Chunk, noise: np.ndarray, maxima: _Maxima, half: int) -> tuple[np.ndarray, ...]:
    """(frame, row, col, snr, close_pair) of the maxima of one spot merged (`merge_maxima`)."""
    frame, rows, cols, values = maxima

    def valleys(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        out = np.empty(len(first))
        _k.valleys_in_frames(*chunk.args, frame, rows, cols, first, second, out)
        return out

    keep, close = merge_maxima(frame, rows, cols, values, noise, chunk.sigma, half, valleys)
    snr = values / noise[frame]
    return frame[keep], rows[keep], cols[keep], snr[keep], close[keep]


def merge_maxima(
    frame: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    values: np.ndarray,
    noise: np.ndarray,
    sigma: float,
    half: int,
    valleys: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """(keep, close_pair) of maxima ordered by ``frame``: a maximum within 3 sigma of a higher one
    with no dip of 2 noise units between them is a ripple of the same spot (not kept); a kept one
    with another within ``half`` px is a close pair. ``valleys(first, second)`` gives the lowest
    band-passed value on the line between maxima ``first[k]`` and ``second[k]``.

    The kernels take the maxima of each frame ordered by row (as `detect_frames` writes them;
    others are put in that order here and the flags returned in the given order)."""
    order = np.lexsort((rows, frame))
    in_order = bool(np.all(order == np.arange(len(order))))
    if not in_order:
        frame, rows, cols, values = frame[order], rows[order], cols[order], values[order]
        given = valleys

        def valleys(first: np.ndarray, second: np.ndarray) -> np.ndarray:
            return given(order[first], order[second])

    starts = np.searchsorted(frame, np.arange(len(noise) + 1))
    radius = _MERGE_RADIUS_SIGMAS * sigma
    counts = np.empty(len(rows), np.int64)
    _k.count_higher(starts, rows, cols, values, radius, counts)
    offsets = np.zeros(len(rows) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    higher = np.empty(offsets[-1], np.int64)
    _k.list_higher(starts, rows, cols, values, radius, offsets, higher)
    lows = valleys(np.repeat(np.arange(len(rows)), counts), higher)
    keep = np.empty(len(rows), np.bool_)
    close = np.empty(len(rows), np.bool_)
    _k.merge_and_pair(starts, rows, cols, values, noise, offsets, lows, _MERGE_DIP, half, keep,
                      close)  # fmt: skip
    if in_order:
        return keep, close
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return keep[back], close[back]


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

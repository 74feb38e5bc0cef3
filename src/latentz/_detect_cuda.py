"""CUDA twin of :func:`latentz.detect.detect_arrays`: band-pass, peaks and ROI cutting on the GPU.

The algorithm is the one of :mod:`latentz.detect`, step for step, so that both devices find the
same emitters:

1. band-pass ``G(sigma) - B(B(B(frame)))``: a Gaussian of ``sigma`` (scipy's sampled kernel,
   radius ``int(4 sigma + 0.5)``) minus three box filters standing in for ``G(5 sigma)``, each a
   separable 1D correlation with the frame's edge pixels repeated (scipy's mode "nearest");
2. noise: 1.4826 x the median absolute deviation of the filtered frame (every other pixel in each
   direction above 256 x 256 pixels), taken on the host from a subsample the GPU makes;
3. a local maximum is the largest value within ``min_distance`` pixels and above
   ``threshold x noise``; the GPU lists them, the host orders them as ``np.nonzero`` does;
4. ROI corners and close pairs on the host (a few numbers per spot), the ROIs cut on the GPU.

Frames go through the GPU in batches of bounded size from a pinned host buffer, kept between calls.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numba import cuda

from latentz._cuda_buffers import batch_size, buffer_pair
from latentz._shared.validate import check_int, check_positive
from latentz.detect import (
    _MAD_TO_SIGMA,
    DEFAULT_THRESHOLD,
    Detections,
    _close_pairs,
    _wide_gaussian_width,
    check_frames,
    roi_corners,
)

__all__ = ["detect_arrays_cuda"]

_THREADS_2D = (8, 32)
#: Bytes of float64 frames per batch; the device holds about four such buffers.
_BATCH_BYTES = 128 * 2**20


def gaussian_weights(sigma: float) -> np.ndarray:
    """scipy.ndimage's sampled, normalised Gaussian kernel of ``sigma`` px (truncate 4)."""
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    phi = np.exp(-0.5 / sigma**2 * x**2)
    return phi / phi.sum()


@cuda.jit
def _correlate(src, dst, weights, axis):
    """``dst = src`` correlated with ``weights`` (odd length, centred) along ``axis`` (1 or 2)
    of a (t, H, W) stack, edge pixels repeated (scipy's mode "nearest")."""
    t, i, j = cuda.grid(3)
    n_t, n_i, n_j = src.shape
    if t >= n_t or i >= n_i or j >= n_j:
        return
    half = weights.shape[0] // 2
    acc = 0.0
    for k in range(weights.shape[0]):
        if axis == 1:
            acc += weights[k] * src[t, min(max(i + k - half, 0), n_i - 1), j]
        else:
            acc += weights[k] * src[t, i, min(max(j + k - half, 0), n_j - 1)]
    dst[t, i, j] = acc


@cuda.jit
def _subtract(a, b, out):
    t, i, j = cuda.grid(3)
    if t < out.shape[0] and i < out.shape[1] and j < out.shape[2]:
        out[t, i, j] = a[t, i, j] - b[t, i, j]


@cuda.jit
def _subsample(src, step, dst):
    t, i, j = cuda.grid(3)
    if t < dst.shape[0] and i < dst.shape[1] and j < dst.shape[2]:
        dst[t, i, j] = src[t, i * step, j * step]


@cuda.jit
def _peaks(filtered, limit, reach, count, out):
    """List ``(t, i, j, value)`` where ``filtered`` is the maximum within ``reach`` px and above
    ``limit[t]``; ``count[0]`` counts them (also those beyond the capacity of ``out``)."""
    t, i, j = cuda.grid(3)
    n_t, n_i, n_j = filtered.shape
    if t >= n_t or i >= n_i or j >= n_j:
        return
    value = filtered[t, i, j]
    if not value > limit[t]:
        return
    for ii in range(max(i - reach, 0), min(i + reach + 1, n_i)):
        for jj in range(max(j - reach, 0), min(j + reach + 1, n_j)):
            if filtered[t, ii, jj] > value:
                return
    slot = cuda.atomic.add(count, 0, 1)
    if slot < out.shape[0]:
        out[slot, 0] = t
        out[slot, 1] = i
        out[slot, 2] = j
        out[slot, 3] = value


@cuda.jit
def _cut(frames, frame, row0, col0, rois):
    k, i, j = cuda.grid(3)
    if k < rois.shape[0] and i < rois.shape[1] and j < rois.shape[2]:
        rois[k, i, j] = frames[frame[k], row0[k] + i, col0[k] + j]


def _grid(shape: tuple[int, int, int]) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    block = (1, *_THREADS_2D)
    return tuple(math.ceil(s / b) for s, b in zip(shape, block, strict=True)), block


@functools.cache
def _filter_weights(sigma: float) -> tuple[Any, Any]:
    width = _wide_gaussian_width(5.0 * sigma)
    box = np.full(width, 1.0 / width)
    if width % 2 == 0:  # scipy centres an even box one pixel left of the middle: pad the right
        box = np.append(box, 0.0)
    return cuda.to_device(gaussian_weights(sigma)), cuda.to_device(box)


def _band_pass(d_frames: Any, sigma: float, work: tuple[Any, Any, Any]) -> Any:
    """Band-passed frames (device array, one of ``work``)."""
    gauss, box = _filter_weights(sigma)
    a, b, c = work
    grid, block = _grid(d_frames.shape)
    _correlate[grid, block](d_frames, a, gauss, 1)
    _correlate[grid, block](a, b, gauss, 2)  # b = G(sigma)
    src = d_frames
    for _ in range(3):
        _correlate[grid, block](src, a, box, 1)
        _correlate[grid, block](a, c, box, 2)
        src = c
    _subtract[grid, block](b, c, a)
    return a


def _noise(d_filtered: Any) -> np.ndarray:
    """Robust noise of each filtered frame, as `latentz.detect.noise_level`."""
    n_t, height, width = d_filtered.shape
    step = 2 if height * width > 256 * 256 else 1
    shape = (n_t, -(-height // step), -(-width // step))
    d_sub = cuda.device_array(shape)
    grid, block = _grid(shape)
    _subsample[grid, block](d_filtered, step, d_sub)
    values = d_sub.copy_to_host().reshape(n_t, -1)
    centre = np.median(values, axis=1, keepdims=True)
    noise = _MAD_TO_SIGMA * np.median(np.abs(values - centre), axis=1)
    # a flat frame: fall back on the standard deviation, as find_peaks does
    for t in np.flatnonzero(~(noise > 0)):
        noise[t] = float(np.std(d_filtered[t].copy_to_host())) or 1.0
    return noise


def _find_peaks(d_filtered: Any, limit: np.ndarray, reach: int) -> np.ndarray:
    """(k, 4) float64 (frame, row, col, filtered value) of the maxima, in the order of
    ``np.nonzero``."""
    capacity = 4096
    while True:
        count = cuda.to_device(np.zeros(1, np.int64))
        out = cuda.device_array((capacity, 4), np.float64)
        grid, block = _grid(d_filtered.shape)
        _peaks[grid, block](d_filtered, cuda.to_device(limit), reach, count, out)
        found = int(count.copy_to_host()[0])
        if found <= capacity:
            peaks = out[:found].copy_to_host() if found else np.zeros((0, 4))
            return peaks[np.lexsort(peaks[:, 2::-1].T)]
        capacity = found


def detect_arrays_cuda(
    frames: Any,
    *,
    roi_size: int = 11,
    threshold: float | None = None,
    sigma: float = 1.5,
    min_distance: int = 2,
) -> Detections:
    """:func:`latentz.detect.detect_arrays` on the GPU: same arguments, same `Detections`."""
    stack, roi_size = check_frames(frames, roi_size)
    n_frames, height, width = stack.shape
    threshold = check_positive("threshold", DEFAULT_THRESHOLD if threshold is None else threshold)
    sigma = check_positive("sigma", sigma)
    reach = check_int("min_distance", min_distance, minimum=1)
    batch = batch_size(n_frames, _BATCH_BYTES // (8 * height * width))
    shape = (batch, height, width)
    pinned, d_frames = buffer_pair("frames", shape, np.float64)
    work = tuple(buffer_pair(f"band-pass {k}", shape, np.float64)[1] for k in range(3))
    parts = []
    for first in range(0, n_frames, batch):
        m = min(batch, n_frames - first)
        pinned[:m] = stack[first : first + m]
        d_batch = d_frames[:m]
        d_batch.copy_to_device(pinned[:m])
        filtered = _band_pass(d_batch, sigma, tuple(w[:m] for w in work))
        noise = _noise(filtered)
        peaks = _find_peaks(filtered, threshold * noise, reach)
        t, rows, cols = np.ascontiguousarray(peaks[:, :3].T, dtype=np.int64)
        snr = peaks[:, 3] / noise[t]
        row0, col0, edge = roi_corners(rows, cols, roi_size, (height, width))
        close = np.zeros(len(t), dtype=bool)
        for frame in np.unique(t):
            here = t == frame
            close[here] = _close_pairs(rows[here], cols[here], roi_size // 2)
        rois = np.zeros((len(t), roi_size, roi_size))
        if len(t):
            d_rois = cuda.device_array_like(rois)
            grid, block = _grid(rois.shape)
            _cut[grid, block](
                d_batch, cuda.to_device(t), cuda.to_device(row0), cuda.to_device(col0), d_rois
            )
            rois = d_rois.copy_to_host()
        parts.append((t + first, rows, cols, snr, row0, col0, edge, close, rois))
    columns = [np.concatenate(c) for c in zip(*parts, strict=True)]
    ints = (c.astype(np.int64) for c in columns[:3])
    frame_idx, rows, cols = ints
    return Detections(
        frame_idx,
        rows,
        cols,
        columns[3].astype(np.float64),
        columns[4].astype(np.int64),
        columns[5].astype(np.int64),
        columns[6].astype(bool),
        columns[7].astype(bool),
        columns[8],
    )

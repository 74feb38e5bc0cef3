"""CUDA twin of :func:`latentz.detect.detect_arrays`: band-pass, peaks and ROI cutting on the GPU.

The algorithm is the one of :mod:`latentz.detect`, step for step, so that both devices find the
same emitters:

0. the frames go to the GPU as stored (uint16 from a camera: a quarter of float64's bytes) and
   become photoelectrons there, ``(adu - offset) x gain / flatfield``, as the CPU kernels convert
   each pixel where they read it;
1. band-pass as :func:`latentz.detect.band_pass`: ``G(sigma)`` minus the wide background (block
   means blurred on the shrunk grid, read back bilinearly), each Gaussian a separable 1D
   correlation with the frame's edge pixels repeated;
2. noise: :func:`latentz.detect.band_noise` of the frames, on the host (a sparse grid of pixels);
3. a local maximum is the largest value within ``min_distance`` pixels and above
   ``threshold x noise``; the GPU lists them, the host orders them as ``np.nonzero`` does;
4. the maxima of one spot merged and close pairs flagged on the host (a few numbers per spot),
   the band's minimum between two maxima read on the GPU; ROI corners on the host, the ROIs cut
   on the GPU.

Frames go through the GPU in batches of bounded size from a pinned host buffer, kept between calls.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import cuda, float32

from latentz._shared.cuda_buffers import batch_size, buffer_pair, device_buffer
from latentz._shared.validate import check_int, check_positive
from latentz.detect import _kernels as _detect_kernels
from latentz.detect.api import (
    Detections,
    _camera_terms,
    band_noise,
    check_frames,
    check_noise,
    default_threshold,
    edge_noise_gain,
    filter_plan,
    merge_maxima,
    roi_corners,
)

if TYPE_CHECKING:
    from latentz.camera import Camera

__all__ = ["detect_arrays_cuda"]


_THREADS_2D = (8, 32)
#: Bytes of float64 frames per batch; the device holds about four such buffers.
_BATCH_BYTES = 128 * 2**20


@cuda.jit
def _to_photons(raw, offset, gain, scale, out):
    """``out = (raw - offset) * gain`` of a (t, H, W) stack, or times ``scale[i, j]`` instead of
    the gain where ``scale`` (H, W) holds gain / flatfield (larger than the (1, 1) stand-in of a
    uniform camera), as the CPU kernels convert."""
    t, i, j = cuda.grid(3)
    if t >= out.shape[0] or i >= out.shape[1] or j >= out.shape[2]:
        return
    factor = scale[i, j] if scale.shape[0] > 1 else gain
    out[t, i, j] = (raw[t, i, j] - offset) * factor


_line_pixel = cuda.jit(device=True)(_detect_kernels.line_pixel.py_func)


@cuda.jit
def _valleys(band, frame, rows, cols, first, second, out):
    """``out[k]``: the least band-passed value (as float32, like the CPU's stored band) on the
    line of pixels between maxima ``first[k]`` and ``second[k]``: `valleys_in_frames` on the
    stored band."""
    k = cuda.grid(1)
    if k >= out.shape[0]:
        return
    p, q = first[k], second[k]
    steps = max(abs(rows[q] - rows[p]), abs(cols[q] - cols[p]))
    low = np.inf
    for m in range(steps + 1):
        i, j = _line_pixel(rows[p], cols[p], rows[q], cols[q], m)
        low = min(low, float32(band[frame[p], i, j]))
    out[k] = low


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
def _block_means(src, factor, dst):
    """``dst[t, R, C]``: mean of ``src[t]`` over block ``R, C`` of ``factor`` px (partial blocks
    at the far edges average the pixels they hold), as `latentz.detect.band_pass`."""
    t, big, c = cuda.grid(3)
    n_t, n_i, n_j = src.shape
    if t >= dst.shape[0] or big >= dst.shape[1] or c >= dst.shape[2]:
        return
    acc = 0.0
    r1 = min(big * factor + factor, n_i)
    c1 = min(c * factor + factor, n_j)
    for i in range(big * factor, r1):
        for j in range(c * factor, c1):
            acc += src[t, i, j]
    dst[t, big, c] = acc / ((r1 - big * factor) * (c1 - c * factor))


@cuda.jit
def _subtract_background(small, background, factor, out):
    """``out = small - background`` read bilinearly at ``(i + 0.5) / factor - 0.5`` (clamped)."""
    t, i, j = cuda.grid(3)
    if t >= out.shape[0] or i >= out.shape[1] or j >= out.shape[2]:
        return
    n_r, n_c = background.shape[1], background.shape[2]
    y = min(max((i + 0.5) / factor - 0.5, 0.0), n_r - 1.0)
    x = min(max((j + 0.5) / factor - 0.5, 0.0), n_c - 1.0)
    r0, c0 = int(math.floor(y)), int(math.floor(x))
    r1, c1 = min(r0 + 1, n_r - 1), min(c0 + 1, n_c - 1)
    fy, fx = y - r0, x - c0
    top = background[t, r0, c0] + fx * (background[t, r0, c1] - background[t, r0, c0])
    bottom = background[t, r1, c0] + fx * (background[t, r1, c1] - background[t, r1, c0])
    out[t, i, j] = small[t, i, j] - (top + fy * (bottom - top))


@cuda.jit
def _peaks(filtered, limit, gain_rows, gain_cols, reach, count, out):
    """List ``(t, i, j, value)`` where ``filtered`` is the maximum within ``reach`` px and above
    ``limit[t] * gain_rows[i] * gain_cols[j]``; ``count[0]`` counts them (also those beyond the
    capacity of ``out``)."""
    t, i, j = cuda.grid(3)
    n_t, n_i, n_j = filtered.shape
    if t >= n_t or i >= n_i or j >= n_j:
        return
    value = filtered[t, i, j]
    if not value > limit[t] * gain_rows[i] * gain_cols[j]:
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
def _filter_weights(sigma: float) -> tuple[Any, int, Any]:
    plan = filter_plan(sigma)
    return cuda.to_device(plan.weights), plan.factor, cuda.to_device(plan.wide_weights)


def _band_pass(d_frames: Any, sigma: float, work: tuple[Any, Any, Any]) -> Any:
    """Band-passed frames (device array, one of ``work``): `latentz.detect.band_pass`."""
    gauss, factor, wide = _filter_weights(sigma)
    a, b, c = work
    grid, block = _grid(d_frames.shape)
    _correlate[grid, block](d_frames, a, gauss, 1)
    _correlate[grid, block](a, b, gauss, 2)  # b = G(sigma)
    n_t, height, width = d_frames.shape
    shape = (n_t, -(-height // factor), -(-width // factor))
    shrunk, blurred = cuda.device_array(shape), cuda.device_array(shape)
    small_grid, small_block = _grid(shape)
    _block_means[small_grid, small_block](d_frames, factor, shrunk)
    _correlate[small_grid, small_block](shrunk, blurred, wide, 1)
    _correlate[small_grid, small_block](blurred, shrunk, wide, 2)
    _subtract_background[grid, block](b, shrunk, factor, a)
    return a


def _find_peaks(d_filtered: Any, limit: np.ndarray, sigma: float, reach: int) -> np.ndarray:
    """(k, 4) float64 (frame, row, col, filtered value) of the maxima, in the order of
    ``np.nonzero``."""
    capacity = 4096
    weights = filter_plan(sigma).weights
    _, height, width = d_filtered.shape
    gain_rows = cuda.to_device(edge_noise_gain(height, weights))
    gain_cols = cuda.to_device(edge_noise_gain(width, weights))
    while True:
        count = cuda.to_device(np.zeros(1, np.int64))
        out = cuda.device_array((capacity, 4), np.float64)
        grid, block = _grid(d_filtered.shape)
        _peaks[grid, block](
            d_filtered, cuda.to_device(limit), gain_rows, gain_cols, reach, count, out
        )
        found = int(count.copy_to_host()[0])
        if found <= capacity:
            peaks = out[:found].copy_to_host() if found else np.zeros((0, 4))
            return peaks[np.lexsort(peaks[:, 2::-1].T)]
        capacity = found


def _device_valleys(d_band: Any, t: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> Any:
    """`merge_maxima`'s ``valleys`` for maxima ``(t, rows, cols)`` of the device band."""
    d_t, d_rows, d_cols = (cuda.to_device(np.ascontiguousarray(a)) for a in (t, rows, cols))

    def valleys(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        out = np.empty(len(first))
        if len(first):
            d_out = cuda.device_array(len(first))
            blocks = math.ceil(len(first) / 128)
            _valleys[blocks, 128](
                d_band, d_t, d_rows, d_cols, cuda.to_device(np.asarray(first, np.int64)),
                cuda.to_device(np.asarray(second, np.int64)), d_out,
            )  # fmt: skip
            out = d_out.copy_to_host()
        return out

    return valleys


def detect_arrays_cuda(
    frames: Any,
    *,
    roi_size: int = 11,
    threshold: float | None = None,
    sigma: float = 1.5,
    min_distance: int = 2,
    noise: Any = None,
    camera: Camera | None = None,
) -> Detections:
    """:func:`latentz.detect.detect_arrays` on the GPU: same arguments, same `Detections`; frames
    as stored (ADU when ``camera`` is given), the ROIs in photoelectrons."""
    stack, roi_size = check_frames(frames, roi_size)
    n_frames, height, width = stack.shape
    if threshold is None:
        threshold = default_threshold(height, width)
    threshold = check_positive("threshold", threshold)
    sigma = check_positive("sigma", sigma)
    reach = check_int("min_distance", min_distance, minimum=1)
    noise_known = check_noise(noise, n_frames)
    offset, gain, scale = _camera_terms((height, width), camera)
    d_scale = cuda.to_device(scale if scale.size else np.ones((1, 1), np.float32))
    batch = batch_size(n_frames, _BATCH_BYTES // (8 * height * width))
    shape = (batch, height, width)
    pinned, d_raw = buffer_pair("frames", shape, stack.dtype)
    photons, *work = (device_buffer(f"band-pass {k}", shape, np.float64) for k in range(4))
    parts = []
    for first in range(0, n_frames, batch):
        m = min(batch, n_frames - first)
        pinned[:m] = stack[first : first + m]
        d_raw[:m].copy_to_device(pinned[:m])
        d_batch = photons[:m]
        grid, block = _grid(d_batch.shape)
        _to_photons[grid, block](d_raw[:m], offset, gain, d_scale, d_batch)
        filtered = _band_pass(d_batch, sigma, tuple(w[:m] for w in work))
        noise = (
            noise_known[first : first + m]
            if noise_known is not None
            else band_noise(stack[first : first + m], sigma=sigma, camera=camera)
        )
        peaks = _find_peaks(filtered, threshold * noise, sigma, reach)
        t, rows, cols = np.ascontiguousarray(peaks[:, :3].T, dtype=np.int64)
        values = peaks[:, 3].copy()
        valleys = _device_valleys(filtered, t, rows, cols)
        keep, close = merge_maxima(t, rows, cols, values, noise, sigma, roi_size // 2, valleys)
        t, rows, cols, close, values = t[keep], rows[keep], cols[keep], close[keep], peaks[keep, 3]
        snr = values / noise[t]
        row0, col0, edge = roi_corners(rows, cols, roi_size, (height, width))
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

"""numba kernels of detection: band-pass, noise level, local maxima and pair flags, per chunk.

The NumPy reference twins are :func:`latentz.detect.band_pass`, :func:`latentz.detect.noise_level`
and :func:`latentz.detect.find_peaks`; the filter is defined once, by
:func:`latentz.detect.filter_plan`. Work is split into (frame, strip of rows) tasks run in
parallel (``numba.prange``), so a chunk of one frame still uses every core. Everything is float32:
the band-passed frame only decides where maxima are.

Per task, the small Gaussian runs in one pass: each input row is filtered horizontally into a ring
of ``2 r + 1`` rows, and each output row is filtered vertically from that ring, minus the wide
background, which is blurred on a frame shrunk by block means and read back by bilinear
interpolation.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_FASTMATH = {"nsz", "arcp", "contract", "reassoc", "afn"}


@numba.njit(cache=True, fastmath=_FASTMATH)
def _clip(v, n):
    return 0 if v < 0 else (n - 1 if v >= n else v)


@numba.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def block_means(frames, factor, out):
    """``out[t, R, C]``: mean of ``frames[t]`` over block ``R, C`` of ``factor`` x ``factor``
    pixels (partial blocks at the far edges average the pixels they hold)."""
    n, h, w = frames.shape
    hs, ws = out.shape[1], out.shape[2]
    for task in numba.prange(n * hs):
        t = task // hs
        big = task % hs
        acc = np.zeros(w, dtype=np.float32)
        r1 = min(big * factor + factor, h)
        for i in range(big * factor, r1):
            line = frames[t, i]
            for j in range(w):
                acc[j] += line[j]
        rows = r1 - big * factor
        for c in range(ws):
            c1 = min(c * factor + factor, w)
            total = 0.0
            for j in range(c * factor, c1):
                total += acc[j]
            out[t, big, c] = total / (rows * (c1 - c * factor))


@numba.njit(cache=True, fastmath=_FASTMATH)
def _pad_row(src, r, pad):
    """``pad[r : r + w] = src``, with the edge values repeated ``r`` times on each side."""
    w = src.shape[0]
    for j in range(w):
        pad[r + j] = src[j]
    for j in range(r):
        pad[j] = src[0]
        pad[r + w + j] = src[w - 1]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _row_filter(pad, weights, dst):
    """Horizontal filter of a row padded by `_pad_row` (nearest-edge mode) into ``dst``."""
    w = dst.shape[0]
    for j in range(w):
        dst[j] = 0.0
    for k in range(len(weights)):
        wk = weights[k]
        for j in range(w):
            dst[j] += wk * pad[j + k]


@numba.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def blur(images, weights, out):
    """Separable filter of each image with symmetric ``weights`` (2 r + 1), nearest-edge mode."""
    n, h, w = images.shape
    r = (len(weights) - 1) // 2
    for t in numba.prange(n):
        tmp = np.empty((h, w), dtype=np.float32)
        pad = np.empty(w + 2 * r, dtype=np.float32)
        for i in range(h):
            _pad_row(images[t, i], r, pad)
            _row_filter(pad, weights, tmp[i])
        for i in range(h):
            line = out[t, i]
            for j in range(w):
                line[j] = 0.0
            for k in range(-r, r + 1):
                wk = weights[k + r]
                src = tmp[_clip(i + k, h)]
                for j in range(w):
                    line[j] += wk * src[j]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _interp_axis(n, factor, n_small, index0, index1, frac):
    """Bilinear sampling of a block-mean axis: pixel centre ``i`` sits at ``(i + 0.5) / f - 0.5``
    in block units, clamped to the first and last block."""
    for i in range(n):
        pos = (i + 0.5) / factor - 0.5
        pos = min(max(pos, 0.0), n_small - 1.0)
        i0 = int(math.floor(pos))
        index0[i] = i0
        index1[i] = min(i0 + 1, n_small - 1)
        frac[i] = pos - i0


@numba.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def band_pass_strips(frames, background, factor, weights, n_strips, dog):
    """``dog[t] = G_sigma * frames[t] - background`` (float32), in (frame, strip) tasks.

    ``background`` (n, hs, ws) is the blurred block-mean image, read by bilinear interpolation.
    """
    n, h, w = frames.shape
    hs, ws = background.shape[1], background.shape[2]
    r = (len(weights) - 1) // 2
    ring_n = 2 * r + 1
    for task in numba.prange(n * n_strips):
        t = task // n_strips
        s = task % n_strips
        a = s * h // n_strips
        b = (s + 1) * h // n_strips
        col0 = np.empty(w, dtype=np.int64)
        col1 = np.empty(w, dtype=np.int64)
        colf = np.empty(w, dtype=np.float32)
        _interp_axis(w, factor, ws, col0, col1, colf)
        ring = np.empty((ring_n, w), dtype=np.float32)
        pad = np.empty(w + 2 * r, dtype=np.float32)
        top = np.empty(w, dtype=np.float32)
        bottom = np.empty(w, dtype=np.float32)
        for v in range(a - r, a + r):
            _pad_row(frames[t, _clip(v, h)], r, pad)
            _row_filter(pad, weights, ring[(v + ring_n) % ring_n])
        last = -1
        for i in range(a, b):
            v = i + r
            _pad_row(frames[t, _clip(v, h)], r, pad)
            _row_filter(pad, weights, ring[v % ring_n])
            pos = min(max((i + 0.5) / factor - 0.5, 0.0), hs - 1.0)
            r0 = int(math.floor(pos))
            fy = pos - r0
            if r0 != last:  # background rows, upsampled along the row once per block row
                b0 = background[t, r0]
                b1 = background[t, min(r0 + 1, hs - 1)]
                for j in range(w):
                    fx = colf[j]
                    top[j] = b0[col0[j]] + fx * (b0[col1[j]] - b0[col0[j]])
                    bottom[j] = b1[col0[j]] + fx * (b1[col1[j]] - b1[col0[j]])
                last = r0
            out = dog[t, i]
            for j in range(w):
                out[j] = -(top[j] + fy * (bottom[j] - top[j]))
            for k in range(ring_n):
                wk = weights[k]
                line = ring[(i - r + k + ring_n) % ring_n]
                for j in range(w):
                    out[j] += wk * line[j]


@numba.njit(parallel=True, cache=True)
def noise_levels(dog, stride, mad_to_sigma, out):
    """``out[t]``: 1.4826 x median absolute deviation of ``dog[t, ::stride, ::stride]``."""
    n, h, w = dog.shape
    nh = (h + stride - 1) // stride
    nw = (w + stride - 1) // stride
    for t in numba.prange(n):
        values = np.empty(nh * nw)
        k = 0
        for i in range(0, h, stride):
            for j in range(0, w, stride):
                values[k] = dog[t, i, j]
                k += 1
        centre = np.median(values)
        for m in range(nh * nw):
            values[m] = abs(values[m] - centre)
        out[t] = mad_to_sigma * np.median(values)


@numba.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def local_maxima(dog, limits, gain_rows, gain_cols, radius, n_strips, rows, cols, values, counts):
    """Pixels above ``limits[t] * gain_rows[i] * gain_cols[j]`` (the noise grows at the edges,
    `latentz.detect.edge_noise_gain`) that are the largest within ``radius`` px (Chebyshev; ties
    all kept), per (frame, strip) task. Task ``k`` writes its first ``rows.shape[1]`` maxima to row
    ``k`` of ``rows, cols, values`` and its full count to ``counts[k]``."""
    n, h, w = dog.shape
    cap = rows.shape[1]
    for task in numba.prange(n * n_strips):
        t = task // n_strips
        s = task % n_strips
        limit = limits[t]
        found = 0
        for i in range(s * h // n_strips, (s + 1) * h // n_strips):
            line = dog[t, i]
            row_limit = limit * gain_rows[i]
            for j in range(w):
                v = line[j]
                if not v > row_limit * gain_cols[j]:
                    continue
                peak = True
                for ii in range(max(i - radius, 0), min(i + radius + 1, h)):
                    for jj in range(max(j - radius, 0), min(j + radius + 1, w)):
                        if dog[t, ii, jj] > v:
                            peak = False
                            break
                    if not peak:
                        break
                if peak:
                    if found < cap:
                        rows[task, found] = i
                        cols[task, found] = j
                        values[task, found] = v
                    found += 1
        counts[task] = found


@numba.njit(cache=True)
def _valley(dog_t, r0, c0, r1, c1):
    """Lowest value of ``dog_t`` on the straight line between two pixels (nearest pixels)."""
    steps = max(abs(r1 - r0), abs(c1 - c0))
    low = np.inf
    for k in range(steps + 1):
        f = k / steps if steps > 0 else 0.0
        v = dog_t[int(round(r0 + f * (r1 - r0))), int(round(c0 + f * (c1 - c0)))]
        low = min(low, v)
    return low


@numba.njit(parallel=True, cache=True)
def merge_and_pair(dog, starts, rows, cols, values, noise, merge_radius, dip, half, keep, close):
    """Per frame (peaks of frame ``t`` are ``starts[t]:starts[t + 1]``):

    ``keep`` is False for a maximum within ``merge_radius`` px of a higher one with no dip of at
    least ``dip`` noise units between them (noise ripples on one wide spot, not two emitters);
    ``close`` is True for a kept maximum with another kept one within ``half`` px (Chebyshev).
    """
    n_frames = len(starts) - 1
    for t in numba.prange(n_frames):
        a = starts[t]
        b = starts[t + 1]
        for p in range(a, b):
            keep[p] = True
            close[p] = False
        for p in range(a, b):
            for q in range(a, b):
                if q == p or values[q] < values[p] or (values[q] == values[p] and q > p):
                    continue
                dr = rows[q] - rows[p]
                dc = cols[q] - cols[p]
                if dr * dr + dc * dc > merge_radius * merge_radius:
                    continue
                low = _valley(dog[t], rows[p], cols[p], rows[q], cols[q])
                if values[p] - low < dip * noise[t]:
                    keep[p] = False
                    break
        for p in range(a, b):
            if not keep[p]:
                continue
            for q in range(a, b):
                if q != p and keep[q]:
                    if abs(rows[q] - rows[p]) <= half and abs(cols[q] - cols[p]) <= half:
                        close[p] = True
                        break

"""numba kernels of detection: camera transform, band-pass, noise, local maxima, merging, ROIs.

The NumPy reference twins are :func:`latentz.detect.band_pass` and
:func:`latentz.detect.find_peaks`; the filter is defined once, by
:func:`latentz.detect.filter_plan`. Frames come in as they are stored (uint16 ADU, or float
photoelectrons) and each pixel is converted to photoelectrons, ``(value - offset) * gain`` or
``(value - offset) * scale[i, j]`` with ``scale = gain / flatfield``, where it is read: no
photoelectron copy of a chunk is made. Everything is float32: the band-passed frame only decides
where maxima are.

Detection of a chunk is one streaming pass, `detect_frames`, in parallel (``numba.prange``) over
(frame, strip of rows) tasks, so that a chunk of one frame still uses every core. Each input row
is converted and filtered horizontally into a ring of ``2 r + 1`` rows; ahead of it the wide
background streams from block means (`_wide_row`: ``factor`` rows summed, read a second time
from cache, and filtered along the block row into a ring of block rows; `_background_row` blurs
that ring vertically when a band row needs the block row); each band-passed row (the ring
filtered vertically, minus the background read back bilinearly) goes into a second ring of
``2 d + 1`` rows, ``d`` the maxima's radius; each row whose ``d`` rows below are ready is tested
(`_row_maxima`: the pixels above the floor counted first, which vectorises; in a row holding
some, only the spans of `_SPAN` columns that do are compared with their neighbours). Memory is
a few rows per task; the band-passed frame is never stored.

The threshold is known before the pass: the noise comes from the pixels
(:func:`latentz.detect.band_noise`, in NumPy on a sparse grid).

The maxima of one wide spot are merged afterwards, on one thread (a few dozen per frame: waking
the other threads would cost more than the work): `count_higher` and `list_higher` pair each
maximum with the higher ones near it, `valleys_in_frames` finds the lowest band-passed value on
the line between them (recomputed at those few pixels), and `merge_and_pair` drops ripples and
flags close pairs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_FASTMATH = {"nsz", "arcp", "contract", "reassoc", "afn"}


@numba.njit(cache=True, fastmath=_FASTMATH)
def _clip(v, n):
    return 0 if v < 0 else (n - 1 if v >= n else v)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _photon_row(src, offset, gain, scale, i, dst, start):
    """``dst[start : start + w]``: row ``src`` (frame row ``i``) in photoelectrons, float32.
    ``scale`` (H, W) is ``gain / flatfield``, or empty for a uniform camera. Written through a
    view: an index ``start + j`` may be negative to numba, and its wraparound test stops LLVM
    vectorising (6x slower)."""
    w = src.shape[0]
    out = dst[start : start + w]
    if scale.shape[0] == 0:
        for j in range(w):
            out[j] = (np.float32(src[j]) - offset) * gain
    else:
        line = scale[i]
        for j in range(w):
            out[j] = (np.float32(src[j]) - offset) * line[j]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _add_photon_row(src, offset, gain, scale, i, acc):
    """``acc += `` row ``src`` (frame row ``i``) in photoelectrons, as `_photon_row`."""
    w = src.shape[0]
    if scale.shape[0] == 0:
        for j in range(w):
            acc[j] += (np.float32(src[j]) - offset) * gain
    else:
        line = scale[i]
        for j in range(w):
            acc[j] += (np.float32(src[j]) - offset) * line[j]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _photon_at(frame, offset, gain, scale, i, j):
    if scale.shape[0] == 0:
        return (np.float32(frame[i, j]) - offset) * gain
    return (np.float32(frame[i, j]) - offset) * scale[i, j]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _block_row_means(acc, factor, rows, out):
    """``out[C]``: the sums of ``rows`` rows in ``acc`` over blocks of ``factor`` columns, as
    means per pixel (float32 sums; the whole blocks first, then a partial one at the end).
    The default sigma's factor (4 at 1.5 px) is passed on as a constant, which LLVM unrolls:
    0.2 against 0.74 ms per 2048 x 2048 frame for a factor known only at run time."""
    if factor == 4:
        _block_means_of(acc, 4, rows, out)
    else:
        _block_means_of(acc, factor, rows, out)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _block_means_of(acc, factor, rows, out):
    """`_block_row_means`, inlined where ``factor`` is a constant."""
    w = acc.shape[0]
    whole = w // factor
    inverse = np.float32(1.0 / (rows * factor))
    for c in range(whole):
        total = np.float32(0.0)
        for m in range(factor):
            total += acc[c * factor + m]
        out[c] = total * inverse
    if whole < out.shape[0]:
        total = np.float32(0.0)
        for j in range(whole * factor, w):
            total += acc[j]
        out[whole] = total / np.float32(rows * (w - whole * factor))


@numba.njit(cache=True, fastmath=_FASTMATH)
def _row_filter(pad, weights, dst):
    """Horizontal filter of a row padded by ``r`` edge values on each side into ``dst``, one
    pass per tap (pairing the symmetric taps, ``pad[j + 2 r - k]``, stops LLVM vectorising: 6x
    slower)."""
    w = dst.shape[0]
    for j in range(w):
        dst[j] = 0.0
    for k in range(len(weights)):
        wk = weights[k]
        for j in range(w):
            dst[j] += wk * pad[j + k]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _row_filter_taps(pad, taps, dst):
    """`_row_filter` with the weights as a tuple (``taps``): its length is known when the kernel
    is compiled (once per length), so the taps unroll and each output pixel is summed in a
    register, twice as fast as one pass per tap."""
    for j in range(dst.shape[0]):
        acc = np.float32(0.0)
        for k in range(len(taps)):
            acc += taps[k] * pad[j + k]
        dst[j] = acc


@numba.njit(cache=True, fastmath=_FASTMATH)
def _pad_edges(pad, r, w):
    for j in range(r):
        pad[j] = pad[r]
        pad[r + w + j] = pad[r + w - 1]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _block_position(i, factor, n_small):
    """Pixel centre ``i`` in block units, ``(i + 0.5) / factor - 0.5``, clamped to the first and
    last of ``n_small`` blocks (bilinear sampling of the block means)."""
    return min(max((i + 0.5) / factor - 0.5, 0.0), n_small - 1.0)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _interp_axis(n, factor, n_small, index0, index1, frac):
    """Bilinear sampling of a block-mean axis at pixels ``0 .. n - 1`` (`_block_position`)."""
    for i in range(n):
        pos = _block_position(i, factor, n_small)
        i0 = int(math.floor(pos))
        index0[i] = i0
        index1[i] = min(i0 + 1, n_small - 1)
        frac[i] = pos - i0


@numba.njit(cache=True, fastmath=_FASTMATH)
def _upsample_row(small, factor, index0, index1, frac, out):
    """``out``: a row of block means of ``factor`` px read bilinearly at each pixel
    (`_interp_axis`). With the default sigma's factor, 4, the pixels between the centres of
    blocks ``c`` and ``c + 1`` (``4 c + 2`` to ``4 c + 5``: exact in binary) are read as one run
    from the two means, without gathering them per pixel (0.35 against 0.75 ms per 2048 x 2048
    frame); other factors gather (their block positions, rounded, may shift a pixel between
    runs)."""
    if factor != 4:
        _upsample_span(small, index0, index1, frac, out, 0, out.shape[0])
        return
    w = out.shape[0]
    inner = max(min(small.shape[0] - 1, (w - 2) // 4), 0)  # whole runs of 4 pixels
    _upsample_span(small, index0, index1, frac, out, 0, min(2, w))
    for c in range(inner):
        a = small[c]
        d = small[c + 1] - a
        run = out[4 * c + 2 : 4 * c + 6]
        weights = frac[4 * c + 2 : 4 * c + 6]
        for m in range(4):
            run[m] = a + weights[m] * d
    _upsample_span(small, index0, index1, frac, out, min(4 * inner + 2, w), w)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _upsample_span(small, index0, index1, frac, out, start, stop):
    """`_upsample_row` of pixels ``start:stop``, gathering each pixel's two block means."""
    for j in range(start, stop):
        a = small[index0[j]]
        out[j] = a + frac[j] * (small[index1[j]] - a)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _background_at(background, factor, i, j):
    """The wide background (one frame's blurred block means) at pixel ``(i, j)``, bilinearly."""
    hs, ws = background.shape
    pr = _block_position(i, factor, hs)
    pc = _block_position(j, factor, ws)
    r0, c0 = int(math.floor(pr)), int(math.floor(pc))
    r1, c1 = min(r0 + 1, hs - 1), min(c0 + 1, ws - 1)
    fy, fx = pr - r0, pc - c0
    top = background[r0, c0] + fx * (background[r0, c1] - background[r0, c0])
    bottom = background[r1, c0] + fx * (background[r1, c1] - background[r1, c0])
    return top + fy * (bottom - top)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _wide_row(frame, offset, gain, scale, factor, wide, big, acc, pad, out):
    """``out``: block row ``big`` of ``frame``'s block means (``factor`` x ``factor`` px, in
    photoelectrons; partial blocks at the far edges average the pixels they hold), filtered
    along the row by ``wide`` (nearest edge). ``acc`` (W) and ``pad`` (len(out) + len(wide) - 1)
    are work rows."""
    h = frame.shape[0]
    rw = (len(wide) - 1) // 2
    ws = out.shape[0]
    acc[:] = 0.0
    r1 = min(big * factor + factor, h)
    for i in range(big * factor, r1):
        _add_photon_row(frame[i], offset, gain, scale, i, acc)
    _block_row_means(acc, factor, r1 - big * factor, pad[rw : rw + ws])
    _pad_edges(pad, rw, ws)
    _row_filter(pad, wide, out)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _background_row(
    frame, offset, gain, scale, factor, wide, big, made, ring, acc, pad, out,
):  # fmt: skip
    """``out``: block row ``big`` of the wide background (the block means blurred by ``wide``
    both ways, nearest edge). ``ring[k % len(ring)]`` holds the row-filtered block rows ``k <
    made``; the rows up to ``big + r`` are added to it first. Returns the new ``made``: block
    rows are asked for in increasing order, each made once."""
    n = ring.shape[0]
    rw = (len(wide) - 1) // 2
    hs = (frame.shape[0] + factor - 1) // factor
    while made <= min(big + rw, hs - 1):
        _wide_row(frame, offset, gain, scale, factor, wide, made, acc, pad, ring[made % n])
        made += 1
    out[:] = 0.0
    for k in range(-rw, rw + 1):
        wk = wide[k + rw]
        src = ring[_clip(big + k, hs) % n]
        for j in range(out.shape[0]):
            out[j] += wk * src[j]
    return made


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def neighbour_differences(frames, offset, gain, scale, step, out):
    """``out[t, p, q]``: the photoelectrons of pixel ``(1 + p step, 1 + q step)`` of frame ``t``
    less the mean of its eight neighbours, times 9 / 8 (each pixel converted where it is read,
    as `detect_frames` does)."""
    for t in numba.prange(frames.shape[0]):
        frame = frames[t]
        for p in range(out.shape[1]):
            i = 1 + p * step
            for q in range(out.shape[2]):
                j = 1 + q * step
                around = np.float32(0.0)
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        around += _photon_at(frame, offset, gain, scale, i + di, j + dj)
                out[t, p, q] = 1.125 * _photon_at(frame, offset, gain, scale, i, j) - 0.125 * around


@numba.njit(cache=True)
def clipped_spreads(values, centre, spread, clip, clipped_variance, rounds):
    """In place, each row ``t`` of ``values`` (t, n): ``rounds`` times, the mean and standard
    deviation of the values within ``clip`` x ``spread[t]`` of ``centre[t]`` (the mean the
    next centre, the deviation over sqrt(``clipped_variance``) the next spread)."""
    for t in range(values.shape[0]):
        c, s = centre[t], spread[t]
        for _ in range(rounds):
            total, square, count = 0.0, 0.0, 0
            for v in values[t]:
                d = v - c
                if abs(d) < clip * s:
                    total += d
                    square += d * d
                    count += 1
            if count == 0:
                break
            mean = total / count
            c += mean
            s = math.sqrt(max(square / count - mean * mean, 0.0) / clipped_variance)
        spread[t] = s if count > 0 else 0.0


@numba.njit(cache=True, fastmath=_FASTMATH)
def _band_row(ring, weights, i, r, top, bottom, fy, out):
    """``out``: band-passed row ``i`` from the ring of horizontally filtered rows, minus the
    background row interpolated between ``top`` and ``bottom``."""
    w = out.shape[0]
    ring_n = ring.shape[0]
    centre = ring[i % ring_n]
    wc = weights[r]
    for j in range(w):
        out[j] = wc * centre[j] - (top[j] + fy * (bottom[j] - top[j]))
    for k in range(r):  # symmetric weights: rows i - r + k and i + r - k share one multiply
        wk = weights[k]
        above = ring[(i - r + k + ring_n) % ring_n]
        below = ring[(i + r - k) % ring_n]
        for j in range(w):
            out[j] += wk * (above[j] + below[j])


@numba.njit(cache=True, fastmath=_FASTMATH)
def _is_peak(band, i, j, v, radius, h):
    """Whether no pixel within ``radius`` (Chebyshev) of ``(i, j)`` exceeds ``v``; ``band``
    holds band-passed rows ``k`` at ``band[k % len(band)]``."""
    w = band.shape[1]
    n = band.shape[0]
    for ii in range(max(i - radius, 0), min(i + radius + 1, h)):
        slot = ii % n
        for jj in range(max(j - radius, 0), min(j + radius + 1, w)):
            if band[slot, jj] > v:  # indexed in place: a row view per row costs more
                return False
    return True


#: Columns per span of `_row_maxima`: the spans holding no pixel above the floor are skipped.
_SPAN = 256


@numba.njit(cache=True, fastmath=_FASTMATH)
def _count_above(line, row_floor, gain_cols):
    """How many pixels of ``line`` lie above ``row_floor * gain_cols`` (vectorises)."""
    above = 0
    for j in range(line.shape[0]):
        above += line[j] > row_floor * gain_cols[j]
    return above


@numba.njit(cache=True, fastmath=_FASTMATH)
def _row_maxima(band, i, radius, h, row_floor, gain_cols, rows, cols, values, found):
    """Append the maxima of band-passed row ``i`` above ``row_floor * gain_cols[j]`` (`_is_peak`)
    to ``rows, cols, values`` from index ``found`` (as far as they have room); return the new
    count. The row's pixels above are counted first, which vectorises: most rows hold none. In a
    row that holds some, each span of `_SPAN` columns is counted the same way and only the spans
    with pixels above are compared pixel by pixel, up to the last pixel above (a row of noise
    holds one or two: 1.1 against 1.7 ms per 2048 x 2048 frame at 30 spots for whole rows)."""
    w = band.shape[1]
    line = band[i % band.shape[0]]
    above = _count_above(line, row_floor, gain_cols)
    for start in range(0, w, _SPAN):
        if above == 0:
            break
        stop = min(start + _SPAN, w)
        span = line[start:stop]
        gains = gain_cols[start:stop]
        here = _count_above(span, row_floor, gains)
        if here == 0:
            continue
        above -= here
        for j in range(stop - start):
            v = span[j]
            if v > row_floor * gains[j] and _is_peak(band, i, start + j, v, radius, h):
                if found < len(rows):
                    rows[found] = i
                    cols[found] = start + j
                    values[found] = v
                found += 1
    return found


@numba.njit(cache=True, fastmath=_FASTMATH)
def _filtered_row(frame, offset, gain, scale, row, r, taps, pad, out):
    """``out``: frame row ``row`` (clipped to the frame) in photoelectrons, filtered along the
    row by ``taps`` (2 r + 1, nearest edge)."""
    h, w = frame.shape
    row = _clip(row, h)
    _photon_row(frame[row], offset, gain, scale, row, pad, r)
    _pad_edges(pad, r, w)
    _row_filter_taps(pad, taps, out)


@numba.njit(parallel=True, nogil=True, cache=True, fastmath=_FASTMATH)
def detect_frames(
    frames, offset, gain, scale, factor, weights, taps, wide, limits, gain_rows, gain_cols, radius,
    n_strips, rows, cols, values, counts, background,
):  # fmt: skip
    """Band-pass and local maxima of ``frames`` in one streaming pass per (frame, strip of rows)
    task. ``taps`` are ``weights`` as a tuple (`_row_filter_taps`), ``wide`` the
    wide Gaussian on block means of ``factor`` px (`latentz.detect.filter_plan`).

    A maximum is a pixel of frame ``t`` above ``limits[t] * gain_rows[i] * gain_cols[j]`` (the
    noise grows at the edges, `latentz.detect.edge_noise_gain`) that is the largest within
    ``radius`` px (Chebyshev; ties all kept). Task ``k`` writes its first ``rows.shape[1]``
    maxima to row ``k`` of ``rows, cols, values`` and their full count to ``counts[k]``; it also
    writes its rows' share of ``background[t]`` (the wide background on the block grid, which
    `valleys_in_frames` reads).
    """
    n, h, w = frames.shape
    hs, ws = background.shape[1], background.shape[2]
    r = (len(weights) - 1) // 2
    rw = (len(wide) - 1) // 2
    ring_n = 2 * r + 1
    band_n = 2 * radius + 1
    for task in numba.prange(n * n_strips):
        t = task // n_strips
        s = task % n_strips
        a = s * h // n_strips
        b = (s + 1) * h // n_strips
        frame = frames[t]
        floor = limits[t]
        col0 = np.empty(w, dtype=np.int64)
        col1 = np.empty(w, dtype=np.int64)
        colf = np.empty(w, dtype=np.float32)
        _interp_axis(w, factor, ws, col0, col1, colf)
        ring = np.empty((ring_n, w), dtype=np.float32)
        band = np.empty((band_n, w), dtype=np.float32)
        pad = np.empty(w + 2 * r, dtype=np.float32)
        upsampled = np.empty((2, w), dtype=np.float32)
        wide_ring = np.empty((2 * rw + 1, ws), dtype=np.float32)
        wide_pad = np.empty(ws + 2 * rw, dtype=np.float32)
        block = np.empty(ws, dtype=np.float32)
        acc = np.empty(w, dtype=np.float32)
        first = max(a - radius, 0)
        for v in range(first - r, first + r):  # the ring's rows above the first band row
            _filtered_row(frame, offset, gain, scale, v, r, taps, pad, ring[(v + ring_n) % ring_n])
        made = max(int(math.floor(_block_position(first, factor, hs))) - rw, 0)
        ready = first  # next band-passed row to compute
        last = -2  # no block row read yet
        found = 0
        for i in range(a, b):
            while ready <= min(i + radius, h - 1):
                _filtered_row(frame, offset, gain, scale, ready + r, r, taps, pad,
                              ring[(ready + r) % ring_n])  # fmt: skip
                pos = _block_position(ready, factor, hs)
                r0 = int(math.floor(pos))
                if r0 != last:  # background rows, upsampled along the row once per block row;
                    # block row r0 + 1 is the next block row's first: kept in slot (r0 + 1) % 2
                    for big in range(r0 if r0 != last + 1 else r0 + 1, r0 + 2):
                        big = min(big, hs - 1)
                        made = _background_row(frame, offset, gain, scale, factor, wide, big,
                                               made, wide_ring, acc, wide_pad, block)  # fmt: skip
                        if a <= big * factor < b:  # each block row written by one task
                            background[t, big] = block
                        _upsample_row(block, factor, col0, col1, colf, upsampled[big % 2])
                    last = r0
                _band_row(ring, weights, ready, r, upsampled[r0 % 2],
                          upsampled[min(r0 + 1, hs - 1) % 2], pos - r0,
                          band[ready % band_n])  # fmt: skip
                ready += 1
            row_floor = floor * gain_rows[i]
            found = _row_maxima(band, i, radius, h, row_floor, gain_cols, rows[task],
                                cols[task], values[task], found)  # fmt: skip
        counts[task] = found


@numba.njit(cache=True)
def _higher_near(p, q, rows, cols, values, merge_radius):
    """Whether maximum ``q`` is higher than ``p`` (ties: the earlier one) and within
    ``merge_radius`` px of it."""
    if q == p or values[q] < values[p] or (values[q] == values[p] and q > p):
        return False
    dr = rows[q] - rows[p]
    dc = cols[q] - cols[p]
    return dr * dr + dc * dc <= merge_radius * merge_radius


@numba.njit(cache=True)
def _rows_near(first, stop, rows, p, merge_radius):
    """From ``first``, the first maximum of ``first:stop`` (ordered by row) whose row is within
    ``merge_radius`` of maximum ``p``'s or below it; the scan ends where a row lies beyond."""
    while first < stop and rows[first] < rows[p] - merge_radius:
        first += 1
    return first


@numba.njit(cache=True)
def count_higher(starts, rows, cols, values, merge_radius, counts):
    """``counts[p]``: the maxima of the same frame higher than ``p`` within ``merge_radius``.
    The maxima of each frame are ordered by row: only the rows within reach are scanned."""
    for t in range(len(starts) - 1):
        first = starts[t]
        for p in range(starts[t], starts[t + 1]):
            first = _rows_near(first, starts[t + 1], rows, p, merge_radius)
            k = 0
            q = first
            while q < starts[t + 1] and rows[q] <= rows[p] + merge_radius:
                k += _higher_near(p, q, rows, cols, values, merge_radius)
                q += 1
            counts[p] = k


@numba.njit(cache=True)
def list_higher(starts, rows, cols, values, merge_radius, offsets, higher):
    """``higher[offsets[p] : offsets[p + 1]]``: the maxima counted by `count_higher`, in order."""
    for t in range(len(starts) - 1):
        first = starts[t]
        for p in range(starts[t], starts[t + 1]):
            first = _rows_near(first, starts[t + 1], rows, p, merge_radius)
            k = offsets[p]
            q = first
            while q < starts[t + 1] and rows[q] <= rows[p] + merge_radius:
                if _higher_near(p, q, rows, cols, values, merge_radius):
                    higher[k] = q
                    k += 1
                q += 1


@numba.njit(cache=True)
def line_pixel(r0, c0, r1, c1, k):
    """Pixel ``k`` of the ``max(|dr|, |dc|) + 1`` nearest pixels on the line between two."""
    steps = max(abs(r1 - r0), abs(c1 - c0))
    f = k / steps if steps > 0 else 0.0
    return int(round(r0 + f * (r1 - r0))), int(round(c0 + f * (c1 - c0)))


@numba.njit(cache=True, fastmath=_FASTMATH)
def _band_at(frame, offset, gain, scale, background, factor, weights, i, j):
    """The band-passed frame at pixel ``(i, j)``, computed there alone."""
    h, w = frame.shape
    r = (len(weights) - 1) // 2
    total = np.float32(0.0)
    for k in range(2 * r + 1):
        ii = _clip(i + k - r, h)
        along = np.float32(0.0)
        for m in range(2 * r + 1):
            along += weights[m] * _photon_at(frame, offset, gain, scale, ii, _clip(j + m - r, w))
        total += weights[k] * along
    return total - _background_at(background, factor, i, j)


@numba.njit(cache=True)
def valleys_in_frames(
    frames, offset, gain, scale, background, factor, weights, frame, rows, cols, first, second,
    out,
):  # fmt: skip
    """``out[k]``: the lowest band-passed value on the line from maximum ``first[k]`` to
    ``second[k]`` (both of frame ``frame[first[k]]``), computed at the line's pixels."""
    for k in range(len(first)):
        p, q = first[k], second[k]
        t = frame[p]
        steps = max(abs(rows[q] - rows[p]), abs(cols[q] - cols[p]))
        low = np.inf
        for m in range(steps + 1):
            i, j = line_pixel(rows[p], cols[p], rows[q], cols[q], m)
            v = _band_at(frames[t], offset, gain, scale, background[t], factor, weights, i, j)
            low = min(low, v)
        out[k] = low


@numba.njit(cache=True)
def merge_and_pair(starts, rows, cols, values, noise, offsets, valleys, dip, half, keep, close):
    """Per frame (maxima of frame ``t`` are ``starts[t]:starts[t + 1]``):

    ``keep`` is False for a maximum with no dip of at least ``dip`` noise units towards one of the
    higher maxima near it (``valleys[offsets[p] : offsets[p + 1]]``, the lowest value on the line
    to each): noise ripples on one wide spot, not two emitters; ``close`` is True for a kept
    maximum with another kept one within ``half`` px (Chebyshev). The maxima of each frame are
    ordered by row: only the rows within reach are scanned.
    """
    for t in range(len(starts) - 1):
        a = starts[t]
        b = starts[t + 1]
        for p in range(a, b):
            keep[p] = True
            close[p] = False
            for k in range(offsets[p], offsets[p + 1]):
                if values[p] - valleys[k] < dip * noise[t]:
                    keep[p] = False
                    break
        first = a
        for p in range(a, b):
            first = _rows_near(first, b, rows, p, half)
            if not keep[p]:
                continue
            q = first
            while q < b and rows[q] <= rows[p] + half:  # the rows within reach
                if q != p and keep[q] and abs(cols[q] - cols[p]) <= half:
                    close[p] = True
                    break
                q += 1


@numba.njit(cache=True, nogil=True)
def cut_rois(stack, frame, row0, col0, out):
    """``out[k]`` (float64): the pixels of ``stack[frame[k]]`` from row ``row0[k]`` and column
    ``col0[k]`` on, NaN where they lie outside the frame."""
    h, w = stack.shape[1], stack.shape[2]
    size_r, size_c = out.shape[1], out.shape[2]
    for k in range(out.shape[0]):
        pixels = stack[frame[k]]
        for i in range(size_r):
            r = row0[k] + i
            for j in range(size_c):
                c = col0[k] + j
                out[k, i, j] = pixels[r, c] if 0 <= r < h and 0 <= c < w else np.nan

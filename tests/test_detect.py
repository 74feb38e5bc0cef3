"""Detection: band-pass, noise level, local maxima, ROI cutting, edge and close-pair flags."""

import numba
import numpy as np
import pandas as pd
import pytest
from movie_truth import emitter_movie, match

from latentz.camera import Camera
from latentz.detect._kernels import line_pixel
from latentz.detect.api import (
    DEFAULT_THRESHOLD,
    band_noise,
    band_pass,
    cut_rois,
    default_threshold,
    detect,
    detect_arrays,
    edge_noise_gain,
    filter_plan,
    find_peaks,
    merge_maxima,
    pixel_noise,
    roi_corners,
    white_noise_gain,
)
from latentz.fit import render_rois


def _spot_frame(
    points, shape=(64, 64), photons=3000.0, background=20.0, seed=0, widths=1.3, noisy=True
):
    """A frame holding round spots (sd ``widths`` px) at the given (x, y) points, with Poisson
    noise unless not ``noisy``."""
    table = pd.DataFrame(
        {"x": [p[0] for p in points], "y": [p[1] for p in points], "photons": photons,
         "background": 0.0, "wx": widths, "wy": widths, "rho": 0.0}
    )  # fmt: skip
    expected = np.full(shape, float(background))
    half = 12
    for k in range(len(table)):
        # a 25 x 25 patch per spot (4 sd of the widest, 3 px), pasted at its pixel
        col, row = int(table.x[k]), int(table.y[k])
        local = table.iloc[[k]].assign(x=table.x[k] - col + half, y=table.y[k] - row + half)
        patch = render_rois(local, shape=2 * half + 1)[0]
        r0, c0 = row - half, col - half
        rs = slice(max(r0, 0), min(r0 + 2 * half + 1, shape[0]))
        cs = slice(max(c0, 0), min(c0 + 2 * half + 1, shape[1]))
        expected[rs, cs] += patch[rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]
    return np.random.default_rng(seed).poisson(expected).astype(float) if noisy else expected


def test_band_pass_removes_a_constant_and_a_slope():
    rows, cols = np.indices((110, 120))
    flat = band_pass(np.full((40, 50), 7.0))
    np.testing.assert_allclose(flat, 0.0, atol=1e-12)
    ramp = band_pass(3.0 + 0.1 * cols + 0.05 * rows)
    # beyond the filters' reach (4 x 7.5 px) from the edges, a symmetric filter passes a linear
    # background unchanged, so the difference cancels it
    np.testing.assert_allclose(ramp[40:70, 40:80], 0.0, atol=1e-9)


def test_pixel_noise_is_the_standard_deviation_of_gaussian_noise_on_a_slope():
    rows, cols = np.indices((200, 200))
    values = np.random.default_rng(1).normal(5.0, 2.0, (200, 200)) + 0.3 * cols + 0.1 * rows
    # MAD-based estimate of 198^2 second differences: sampling error near 0.6 %; the slope
    # cancels in a second difference
    assert pixel_noise(values)[0] == pytest.approx(2.0, rel=0.03)


def test_band_noise_is_the_spread_of_band_passed_white_noise():
    # the band-pass's gain on white noise, averaged over its blocks, against the spread of the
    # band-passed frame itself, away from the edges (sampling error near 0.5 %)
    for sigma in (1.0, 1.5, 2.5):
        white = np.random.default_rng(2).normal(0.0, 3.0, (400, 400))
        spread = band_pass(white, sigma=sigma)[50:-50, 50:-50].std()
        assert band_noise(white, sigma=sigma)[0] == pytest.approx(spread, rel=0.03)
        assert white_noise_gain(sigma) == pytest.approx(spread / 3.0, rel=0.03)


def _crowded_frames(n_spots, n_frames=3, seed=0):
    """256 x 256 px frames, each holding ``n_spots`` bright spots (1,000-3,000 photons, sd
    1.3-2.5 px; 250 make about 0.4 per µm² at 100 nm pixels) over 20 photoelectrons per pixel,
    and the same noise without the spots; the spots' (x, y)."""
    rng = np.random.default_rng(seed)
    crowded, empty, points = [], [], []
    for _ in range(n_frames):
        xy = list(zip(rng.uniform(2, 253, n_spots), rng.uniform(2, 253, n_spots), strict=True))
        spots = sum(
            _spot_frame([p], (256, 256), rng.uniform(1000, 3000), 0.0, noisy=False,
                        widths=rng.uniform(1.3, 2.5))
            for p in xy
        )  # fmt: skip
        crowded.append(rng.poisson(spots + 20.0).astype(float))
        empty.append(rng.poisson(np.full((256, 256), 20.0)).astype(float))
        points.append(xy)
    return np.stack(crowded), np.stack(empty), points


def test_crowded_spots_do_not_raise_the_noise():
    crowded, empty, _ = _crowded_frames(250)
    truth = np.sqrt(20.0) * white_noise_gain(1.5)
    np.testing.assert_allclose(band_noise(empty), truth, rtol=0.03)
    # the spots touch few of the pixels' second differences: the noise reads within 15 % of the
    # background's, where the robust spread of the band-passed frame, which the spots' cores
    # and their dark surrounds widen, reads it several times high
    np.testing.assert_allclose(band_noise(crowded), truth, rtol=0.15)
    band = np.stack([band_pass(f) for f in crowded])
    centre = np.median(band, axis=(1, 2), keepdims=True)
    assert np.all(1.4826 * np.median(np.abs(band - centre), axis=(1, 2)) > 2.0 * truth)


def test_dim_spots_among_crowded_bright_ones_are_found():
    # 300-photon spots (sd 1.3 px, 15 x the band-passed noise at their peak) 8 px or more from
    # 120 bright spots per frame: found 98 %; a threshold on the band-passed frame's spread,
    # which those spots widen, finds none of them
    crowded, _, points = _crowded_frames(120, seed=1)
    rng = np.random.default_rng(3)
    dim = []
    for t in range(len(crowded)):
        others = np.array(points[t])
        xy = [p for p in zip(rng.uniform(8, 247, 200), rng.uniform(8, 247, 200), strict=True)
              if np.min(np.hypot(*(others - p).T)) > 8.0][:20]  # fmt: skip
        crowded[t] += rng.poisson(_spot_frame(xy, (256, 256), 300.0, 0.0, noisy=False))
        dim += [(t, x, y) for x, y in xy]
    found = detect_arrays(crowded)
    hits = [np.any((found.frame == t) & (np.hypot(found.col - x, found.row - y) <= 1.5))
            for t, x, y in dim]  # fmt: skip
    assert np.mean(hits) >= 0.9


def test_single_spot_is_found_at_its_pixel():
    frame = _spot_frame([(30.3, 20.8)])
    rows, cols, snr = find_peaks(frame)
    assert list(zip(rows, cols, strict=True)) == [(21, 30)]
    assert snr[0] > 5


def test_rois_are_cut_around_maxima_and_shifted_at_edges():
    frame = _spot_frame([(30.0, 30.0), (1.2, 40.0), (60.0, 62.4)])
    found = detect_arrays(frame, roi_size=9)
    order = np.argsort(found.col)
    edge = found.edge[order]
    assert list(edge) == [True, False, True]
    for k in range(3):
        r0, c0 = found.row0[k], found.col0[k]
        np.testing.assert_array_equal(found.rois[k], frame[r0 : r0 + 9, c0 : c0 + 9])
        assert 0 <= r0 <= 64 - 9 and 0 <= c0 <= 64 - 9
        # the maximum lies inside its ROI
        assert r0 <= found.row[k] < r0 + 9 and c0 <= found.col[k] < c0 + 9


def test_cut_rois_hold_the_pixels_where_they_lie_and_nan_outside_the_frame():
    """Each pixel of a 3 x 20 x 30 stack holds its own code (frame, row, column): every ROI
    pixel is the code of where it lies, NaN where it lies past the frame's edge (corners up to
    5 px outside), for uint16, float32 and read-only stacks."""
    t, r, c = np.indices((3, 20, 30))
    code = 1000 * t + 40 * r + c
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 3, 200)
    row0, col0 = rng.integers(-5, 20, 200), rng.integers(-5, 30, 200)
    rows, cols = row0[:, None, None] + np.arange(5)[:, None], col0[:, None, None] + np.arange(5)
    inside = (rows >= 0) & (rows < 20) & (cols >= 0) & (cols < 30)
    want = np.where(inside, 1000 * frame[:, None, None] + 40 * rows + cols, np.nan)
    assert 0 < inside.mean() < 1
    read_only = code.astype(np.float64)
    read_only.flags.writeable = False
    for stack in (code.astype(np.uint16), code.astype(np.float32), read_only):
        np.testing.assert_array_equal(cut_rois(stack, frame, row0, col0, 5), want)


def test_close_pairs_are_flagged_and_isolated_spots_are_not():
    frame = _spot_frame([(20.0, 20.0), (25.0, 22.0), (45.0, 45.0)])
    table = detect(frame, roi_size=11)
    assert len(table) == 3
    isolated = (table.col == 45) & (table.row == 45)
    assert not table.close_pair[isolated].any()
    assert table.close_pair[~isolated].all()


def test_false_detections_on_pure_noise_are_rare():
    noise = np.random.default_rng(3).poisson(50.0, (10, 128, 128)).astype(float)
    # a 5-sigma threshold on ~Gaussian filtered noise: about one false maximum per ~10^5 pixels
    assert len(detect(noise)) <= 5


def test_detection_finds_dim_isolated_emitters():
    movie, truth = emitter_movie(10, (96, 96), seed=5, photons=(1000.0, 1001.0))
    found = detect(movie)
    hits, false = match(truth, found.rename(columns={"col": "x", "row": "y"}))
    assert hits >= 0.99 * len(truth)
    assert false <= 0.01 * len(found)


def _assert_frame_matches_the_twin(found, t: int, photons: np.ndarray) -> None:
    """Frame ``t`` of the kernels' detections against :func:`find_peaks` on its photoelectrons
    and the ROIs that :func:`roi_corners` puts around its maxima.

    float32 kernels against float64 NumPy: the same maxima, scores to float32 rounding (no
    maximum lies within 1e-3 of the threshold or of a neighbour in these frames)."""
    rows, cols, snr = find_peaks(photons)
    row0, col0, _ = roi_corners(rows, cols, found.rois.shape[1], photons.shape)
    mine = found.frame == t
    got = zip(found.row[mine], found.col[mine], found.row0[mine], found.col0[mine], strict=True)
    assert sorted(got) == sorted(zip(rows, cols, row0, col0, strict=True))
    order = np.lexsort((cols, rows))
    mine_order = np.lexsort((found.col[mine], found.row[mine]))
    np.testing.assert_allclose(found.snr[mine][mine_order], snr[order], rtol=1e-4)


def test_kernels_match_their_numpy_twin():
    # sizes not divisible by the block factor (4 at sigma 1.5) exercise the partial blocks
    rng = np.random.default_rng(11)
    points = list(zip(rng.uniform(3, 257, 25), rng.uniform(3, 197, 25), strict=True))
    frames = np.stack([_spot_frame(points, shape=(201, 261), seed=s) for s in range(3)])
    found = detect_arrays(frames, roi_size=7)
    for t, frame in enumerate(frames):
        _assert_frame_matches_the_twin(found, t, frame)


@pytest.mark.parametrize("factor", [3, 4, 5])
@pytest.mark.parametrize("width", [2048, 2050])
def test_block_means_of_a_row_are_the_twins(factor, width):
    # the kernels' block means (the default factor, 4, compiled as a constant; others not)
    # against the NumPy twin's, whole blocks and a partial one at the row's end
    from latentz.detect import _kernels
    from latentz.detect.api import _block_means

    rows = 3
    acc = np.random.default_rng(factor).uniform(0, 300, width).astype(np.float32)
    out = np.empty(-(-width // factor), np.float32)
    _kernels._block_row_means(acc, factor, rows, out)
    np.testing.assert_allclose(out, _block_means(acc[None] / rows, factor)[0], rtol=1e-6)


@pytest.mark.parametrize("factor", [3, 4, 5])
@pytest.mark.parametrize("width", [5, 261, 2048, 2050])
def test_upsampled_block_rows_are_the_twins(factor, width):
    # the kernels' bilinear reading of a block row (runs of 4 pixels for the default factor, a
    # gather per pixel for others) against the NumPy twin's, at both edges and partial blocks
    from latentz.detect import _kernels
    from latentz.detect.api import _upsampled

    small = np.random.default_rng(width).uniform(0, 100, -(-width // factor)).astype(np.float32)
    index0, index1 = np.empty(width, np.int64), np.empty(width, np.int64)
    frac = np.empty(width, np.float32)
    _kernels._interp_axis(width, factor, len(small), index0, index1, frac)
    out = np.empty(width, np.float32)
    _kernels._upsample_row(small, factor, index0, index1, frac, out)
    expected = _upsampled(small[None].astype(float), (1, width), factor)[0]
    np.testing.assert_allclose(out, expected, rtol=1e-6)


def test_maxima_on_the_kernels_span_boundaries_match_the_twin():
    # the kernels compare pixel by pixel only the spans of `_SPAN` columns holding pixels above
    # the floor: spots whose maxima fall either side of a span's first column
    from latentz.detect._kernels import _SPAN

    xs = [_SPAN - 1.3, _SPAN - 0.6, _SPAN + 0.2, 2 * _SPAN - 0.5, 2 * _SPAN + 0.4, 2 * _SPAN + 8]
    points = [(x, 20.0 + 25.0 * k) for k, x in enumerate(xs)]
    frames = np.stack([_spot_frame(points, shape=(180, 2 * _SPAN + 13), seed=s) for s in range(3)])
    found = detect_arrays(frames, roi_size=7)
    assert np.isin([_SPAN - 1, _SPAN, 2 * _SPAN - 1, 2 * _SPAN], found.col).all()
    for t, frame in enumerate(frames):
        _assert_frame_matches_the_twin(found, t, frame)


def test_kernels_read_adu_frames_as_the_twin_reads_their_photoelectrons():
    # uint16 ADU through a camera with a flatfield, converted where the kernels read each
    # pixel; 530 x 517 px frames: a strided noise sample (every 2nd pixel), partial blocks and
    # several row strips per frame
    rng = np.random.default_rng(12)
    points = list(zip(rng.uniform(3, 514, 40), rng.uniform(3, 527, 40), strict=True))
    photons = np.stack([_spot_frame(points, shape=(530, 517), seed=s) for s in range(3)])
    flat = rng.uniform(0.8, 1.2, photons.shape[1:])
    cam = Camera(offset=100.0, gain=0.5, flatfield=flat)
    adu = np.round(photons * flat / cam.gain + cam.offset).astype(np.uint16)
    found = detect_arrays(adu, roi_size=7, camera=cam)
    for t in range(len(adu)):
        _assert_frame_matches_the_twin(found, t, cam.to_photons(adu[t]))
    # the ROIs are the photoelectrons at their own pixels (float64, the fits' input)
    expected = cut_rois(cam.to_photons(adu), found.frame, found.row0, found.col0, 7)
    np.testing.assert_allclose(found.rois, expected, rtol=1e-12)
    np.testing.assert_allclose(band_noise(adu, camera=cam), band_noise(cam.to_photons(adu)),
                               rtol=1e-4)  # fmt: skip


def test_noise_free_spots_are_found_at_their_pixels():
    # no noise: the band-pass's noise counts as 1 photoelectron
    points = [(20.2, 30.7), (60.0, 12.4), (90.6, 80.1)]
    found = detect(_spot_frame(points, shape=(100, 110), noisy=False))
    assert sorted(zip(found.row, found.col, strict=True)) == [(12, 60), (31, 20), (80, 91)]


def test_the_pass_leaves_the_twins_wide_background_for_the_valleys():
    # the valleys between maxima are recomputed from the wide background the streaming pass
    # writes (every block row by one of several row strips): upsampled as the NumPy twin
    # upsamples its own, it is the small Gaussian minus the twin's band-pass
    from scipy import ndimage

    from latentz.detect import api

    frames = np.random.default_rng(14).poisson(50.0, (2, 530, 517)).astype(float)
    frames += np.linspace(0.0, 80.0, 517)  # a slope, so that the background is not flat
    chunk = api._streamed(frames, 1.5, None, 5.0, 2, None)[0]
    plan = filter_plan(1.5)
    for t, frame in enumerate(frames):
        small = frame
        for axis in (0, 1):
            small = ndimage.correlate1d(small, plan.weights, axis, mode="nearest")
        upsampled = api._upsampled(chunk.background[t].astype(float), frame.shape, plan.factor)
        # float32 sums of ~100 photoelectrons: 1e-4 relative
        np.testing.assert_allclose(upsampled, small - band_pass(frame), rtol=1e-4)


def test_default_threshold_keeps_false_maxima_per_frame_constant():
    assert default_threshold(256, 256) == DEFAULT_THRESHOLD
    assert default_threshold(64, 64) == DEFAULT_THRESHOLD
    u = default_threshold(2048, 2048)
    # area u^2 exp(-u^2/2) is the same at 2048^2 with u as at 256^2 with 5
    assert 64 * u**2 * np.exp(-(u**2) / 2) == pytest.approx(25 * np.exp(-12.5), rel=1e-9)


def test_wide_spots_on_large_frames_give_one_detection_each():
    # issue 14: 30 spots per 2048 x 2048 frame, sd 1.3-3 px, gave ~11 % extra detections: noise
    # maxima over the 64x larger area above a fixed 5-sigma threshold, not split spots
    rng = np.random.default_rng(14)
    frames, truth = [], []
    for t in range(2):
        x, y = rng.uniform(20, 2028, 30), rng.uniform(20, 2028, 30)
        widths = rng.uniform(1.3, 3.0, 30)
        points = list(zip(x, y, strict=True))
        frames.append(_spot_frame(points, (2048, 2048), 5000.0, 50.0, t, widths))
        truth.append(pd.DataFrame({"frame": t, "x": x, "y": y}))
    found = detect(np.stack(frames))
    hits, false = match(pd.concat(truth), found.rename(columns={"col": "x", "row": "y"}))
    assert hits == 60
    # expected false maxima at the area-scaled threshold: about 0.6 per frame at most here
    assert false <= 3


@numba.njit(cache=True)
def valleys_in_band(band, frame, rows, cols, first, second, out):
    """``out[k]``: the least value of stored band-passed frames ``band`` (t, H, W) on the line
    between maxima ``first[k]`` and ``second[k]``, as the kernels' valleys."""
    for k in range(len(first)):
        p, q = first[k], second[k]
        steps = max(abs(rows[q] - rows[p]), abs(cols[q] - cols[p]))
        low = np.inf
        for m in range(steps + 1):
            i, j = line_pixel(rows[p], cols[p], rows[q], cols[q], m)
            low = min(low, band[frame[p], i, j])
        out[k] = low


def test_merging_does_not_depend_on_the_order_of_the_maxima():
    # the kernels take each frame's maxima in row order (the CPU kernels write them so, the GPU
    # in any order): wide spots on noise, whose ripples are merged, in row and in shuffled order
    rng = np.random.default_rng(21)
    points = list(zip(rng.uniform(5, 250, 60), rng.uniform(5, 250, 60), strict=True))
    frames = [_spot_frame(points, (256, 256), 3000.0, 20.0, s, widths=2.8) for s in range(2)]
    band = np.stack([band_pass(f) for f in frames]).astype(np.float32)
    noise = band_noise(np.stack(frames))
    frame, rows, cols = np.nonzero(band > 2.0 * noise[:, None, None])  # every pixel above 2 sd
    values = band[frame, rows, cols].astype(np.float64)

    def flags(order):
        def valleys(first, second):
            out = np.empty(len(first))
            valleys_in_band(band, frame[order], rows[order], cols[order], first, second, out)
            return out

        return merge_maxima(frame[order], rows[order], cols[order], values[order], noise, 2.8,
                            15, valleys)  # fmt: skip

    keep, close = flags(np.arange(len(rows)))
    assert 0 < keep.sum() < len(keep) and close.any()  # ripples dropped, pairs flagged
    shuffled = rng.permutation(len(rows))
    keep_shuffled, close_shuffled = flags(shuffled)
    np.testing.assert_array_equal(keep_shuffled, keep[shuffled])
    np.testing.assert_array_equal(close_shuffled, close[shuffled])


@pytest.mark.parametrize(
    ("frames", "kwargs", "match"),
    [
        (np.zeros((2, 2, 8, 8)), {}, "dimensions"),
        (np.zeros((0, 8, 8)), {}, "non-empty"),
        (np.zeros((8, 8)), {"roi_size": 4}, "odd"),
        (np.zeros((8, 8)), {"roi_size": 11}, "fit in the frames"),
        (np.zeros((16, 16)), {"threshold": 0.0}, "threshold"),
        (np.zeros((16, 16)), {"sigma": -1.0}, "sigma"),
    ],
)
def test_bad_input_raises_clearly(frames, kwargs, match):
    with pytest.raises(ValueError, match=match):
        detect(frames, **kwargs)


def test_false_maxima_are_no_more_frequent_along_the_edges():
    # nearest-edge padding weighs the edge pixel 1.56x in the band-pass (sigma 1.5 px): with one
    # threshold for the whole frame most false maxima lay in the outer two rows and columns
    noise = np.random.default_rng(4).poisson(50.0, (200, 128, 128)).astype(np.float32)
    found = detect_arrays(noise, threshold=3.0, roi_size=5)
    margin = np.minimum.reduce([found.row, found.col, 127 - found.row, 127 - found.col])
    edge_area, inner_area = 128**2 - 124**2, 112**2
    edge_rate = np.sum(margin < 2) / edge_area
    inner_rate = np.sum(margin >= 8) / inner_area
    # ~1100 inner maxima: the ratio's Poisson sd is ~0.1 at a ratio of 1; it was 14x without
    assert edge_rate < 1.5 * inner_rate


def test_edge_noise_gain_is_the_noise_of_band_passed_pure_noise():
    noise = np.random.default_rng(5).poisson(50.0, (40, 128, 128)).astype(float)
    filtered = np.stack([band_pass(frame) for frame in noise])
    gain = edge_noise_gain(128, filter_plan(1.5).weights)
    inner = filtered[:, 20:-20, 20:-20].std()
    assert gain[10:-10] == pytest.approx(1.0)
    # sd of each row's sd about 1.2 % (3520 pixels); the wide background, neglected in the
    # gain, lowers the noise of the outer rows by up to 10 %
    measured = filtered[:, :, 20:-20].std(axis=(0, 2)) / inner
    edge = [0, 1, 2, -3, -2, -1]
    np.testing.assert_allclose(measured[edge], gain[edge], rtol=0.12)
    assert measured[0] > 1.4 and measured[-1] > 1.4


def test_a_given_noise_level_replaces_the_estimate():
    rng = np.random.default_rng(8)
    points = list(zip(rng.uniform(5, 59, 6), rng.uniform(5, 59, 6), strict=True))
    frames = np.stack([_spot_frame(points, seed=s, photons=800.0) for s in range(3)])
    found = detect_arrays(frames)
    noise = band_noise(frames)
    same = detect_arrays(frames, noise=noise)
    np.testing.assert_array_equal(same.row, found.row)
    np.testing.assert_array_equal(same.snr, found.snr)
    # a doubled noise halves every score and keeps only the maxima above twice the threshold
    doubled = detect_arrays(frames, noise=2 * noise)
    np.testing.assert_allclose(np.sort(doubled.snr), np.sort(found.snr[found.snr > 2 * 5.0]) / 2)
    with pytest.raises(ValueError, match="3 values > 0"):
        detect_arrays(frames, noise=noise[:2])

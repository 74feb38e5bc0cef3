"""Detection: band-pass, noise level, local maxima, ROI cutting, edge and close-pair flags."""

import numpy as np
import pandas as pd
import pytest
from movie_truth import emitter_movie, match

from latentz.detect import band_pass, detect, detect_arrays, find_peaks, noise_level
from latentz.fit import render_rois


def _spot_frame(points, shape=(64, 64), photons=3000.0, background=20.0, seed=0):
    """A noisy frame holding round 1.3 px spots at the given (x, y) points."""
    table = pd.DataFrame(
        {"x": [p[0] for p in points], "y": [p[1] for p in points], "photons": photons,
         "background": 0.0, "wx": 1.3, "wy": 1.3, "rho": 0.0}
    )  # fmt: skip
    h, w = shape
    expected = np.full(shape, background)
    for k in range(len(table)):
        # a full-frame "ROI" per spot: exact ground truth in frame coordinates
        expected += render_rois(table.iloc[[k]], shape=(h, w))[0]
    return np.random.default_rng(seed).poisson(expected).astype(float)


def test_band_pass_removes_a_constant_and_a_slope():
    rows, cols = np.indices((110, 120))
    flat = band_pass(np.full((40, 50), 7.0))
    np.testing.assert_allclose(flat, 0.0, atol=1e-12)
    ramp = band_pass(3.0 + 0.1 * cols + 0.05 * rows)
    # beyond the filters' reach (4 x 7.5 px) from the edges, a symmetric filter passes a linear
    # background unchanged, so the difference cancels it
    np.testing.assert_allclose(ramp[40:70, 40:80], 0.0, atol=1e-9)


def test_noise_level_is_the_standard_deviation_of_gaussian_noise():
    values = np.random.default_rng(1).normal(5.0, 2.0, (200, 200))
    # MAD-based estimate: sampling error about 1.65 / sqrt(2 n) relative, 0.6 % here
    assert noise_level(values) == pytest.approx(2.0, rel=0.03)


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

"""Load: `localize` on a movie with about 10x the usual emitter density (many overlaps) finishes,
flags the overlaps it detects, splits or flags those it cannot detect apart, and keeps its
memory within a small multiple of the movie."""

import tracemalloc

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from latentz.detect.api import detect
from latentz.localization import localize

N_FRAMES, SHAPE, N_SPOTS = (
    5,
    (256, 256),
    300,
)  # ~1 spot per 220 px; the gear movies have ~1 per 2000
SIGMA, AMPLITUDE, BACKGROUND = 1.5, 3000.0, 100.0
ROI = 11
HALF = ROI // 2


def dense_movie(seed=3):
    """Poisson frames of eq. 1 spots (round, width SIGMA) at uniform random positions."""
    rng = np.random.default_rng(seed)
    frames = np.empty((N_FRAMES, *SHAPE))
    truth = []
    for t in range(N_FRAMES):
        xy = rng.uniform(3, np.array(SHAPE[::-1]) - 4, (N_SPOTS, 2))
        mu = np.full(SHAPE, BACKGROUND)
        for x, y in xy:
            r0, c0 = int(y) - 8, int(x) - 8
            rows, cols = np.ogrid[
                max(r0, 0) : min(r0 + 18, SHAPE[0]), max(c0, 0) : min(c0 + 18, SHAPE[1])
            ]
            mu[rows, cols] += AMPLITUDE * np.exp(
                -((cols - x) ** 2 + (rows - y) ** 2) / (2 * SIGMA**2)
            )
        frames[t] = rng.poisson(mu)
        truth.append(xy)
    return frames, truth


@pytest.fixture(scope="module")
def dense():
    frames, truth = dense_movie()
    localize(frames[:1], roi_size=ROI)  # compile and warm caches outside the measurement
    tracemalloc.start()
    try:
        locs = localize(frames, roi_size=ROI)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return frames, truth, locs, peak


def test_dense_movie_finishes_with_most_spots_fitted(dense):
    frames, _, locs, _ = dense
    assert set(locs["frame"]) == set(range(N_FRAMES))
    # merged pairs make fewer detections than spots, but most frames' spots are found; a spot
    # is at most one row that is not a duplicate
    unique = len(locs) - locs["duplicate"].sum()
    assert 0.6 * N_SPOTS * N_FRAMES < unique <= N_SPOTS * N_FRAMES
    assert locs["converged"].mean() > 0.9
    finite = locs[locs["converged"]]
    assert np.isfinite(finite[["x", "y", "amplitude", "wx", "wy"]].to_numpy()).all()


def test_memory_stays_within_a_small_multiple_of_the_movie(dense):
    frames, _, _, peak = dense
    # One chunk of float64 frames, a few band-pass temporaries of one frame, and the ROIs
    # (n x ROI^2 float64, about half the movie here): 8x the float64 movie is generous, while
    # anything quadratic in the spots (n^2 or n x frame) would exceed it 10-fold.
    bound = 8 * frames.size * 8
    assert peak < bound, f"peak {peak / 1e6:.1f} MB, bound {bound / 1e6:.1f} MB"


def test_close_pair_is_every_detection_with_another_inside_its_roi(dense):
    frames, _, locs, _ = dense
    found = detect(frames, roi_size=ROI)
    # every row carries its detection's flag: a one-emitter row one detection's, a two-emitter
    # fit's two rows those of the one or more detections whose fits converged on its spot
    single = (locs["pair"] < 0).to_numpy()
    flagged = locs["close_pair"].to_numpy(bool)
    singles = np.bincount(locs["frame"], single & flagged, N_FRAMES)
    pairs = np.bincount(locs["frame"], ~single & flagged, N_FRAMES) / 2
    detections = np.bincount(found["frame"], found["close_pair"], N_FRAMES)
    assert np.all(singles + pairs <= detections), (singles + pairs, detections)
    for t in range(N_FRAMES):
        peaks = found.loc[found["frame"] == t, ["row", "col"]].to_numpy()
        distance = cdist(peaks, peaks, "chebyshev")
        np.fill_diagonal(distance, np.inf)
        expected = distance.min(axis=1) <= HALF
        flags = found.loc[found["frame"] == t, "close_pair"].to_numpy()
        np.testing.assert_array_equal(flags, expected)
    assert locs["close_pair"].mean() > 0.05  # a substantial fraction at this density


def resolved_close_pairs(found, truth, t):
    """True spots with a true neighbour within HALF px, both found as separate detections."""
    frame = found[found["frame"] == t].reset_index(drop=True)
    peaks = frame[["col", "row"]].to_numpy(float)
    distance, nearest = cKDTree(peaks).query(truth[t])
    pairs = cKDTree(truth[t]).query_pairs(HALF, p=np.inf, output_type="ndarray")
    separate = (
        (distance[pairs[:, 0]] <= 1.5)
        & (distance[pairs[:, 1]] <= 1.5)
        & (nearest[pairs[:, 0]] != nearest[pairs[:, 1]])
    )
    return frame, nearest[pairs[separate]]


def test_every_resolved_overlap_is_flagged(dense):
    frames, truth, _, _ = dense
    found = detect(frames, roi_size=ROI)
    n_pairs = 0
    for t in range(N_FRAMES):
        frame, members = resolved_close_pairs(found, truth, t)
        # the detected peaks may be 1 px further apart than the true centres
        peaks = frame[["row", "col"]].to_numpy()
        gap = np.abs(peaks[members[:, 0]] - peaks[members[:, 1]]).max(axis=1)
        inside = gap <= HALF
        assert frame["close_pair"].to_numpy()[members[inside]].all()
        n_pairs += inside.sum()
    assert n_pairs > 0


#: Spots this far apart (px) or more merge into one detection, but the two-emitter fit finds
#: both: measured on 50 isolated pairs of these spots per separation (σ 1.5 px, amplitude 3,000
#: over 100 photons/px, 11 px ROIs), its likelihood ratio's 5th percentile is 175 at 2.3 px
#: (1.5 σ) against a limit of 60, and 46 is its median at 1.8 px. Closer pairs look like one
#: wider spot.
RESOLVED_PX = 2.3


def merged_pairs(locs, truth, t):
    """(frame rows, (a, b), separation px, nearest rows of a and b) for each pair of true
    spots within 2.5 px (Chebyshev) of each other, with no third spot inside the ROI."""
    frame = locs[locs["frame"] == t].reset_index(drop=True)
    distance, nearest = cKDTree(frame[["x", "y"]].to_numpy(float)).query(truth[t])
    spots = cKDTree(truth[t])
    for a, b in spots.query_pairs(2.5, p=np.inf, output_type="ndarray"):
        midpoint = (truth[t][a] + truth[t][b]) / 2
        if len(spots.query_ball_point(midpoint, ROI, p=np.inf)) == 2:
            separation = np.hypot(*(truth[t][a] - truth[t][b]))
            yield frame, (a, b), separation, nearest[[a, b]]


def test_overlaps_are_split_into_two_rows_or_flagged_unresolved(dense):
    """Two spots that merge into one detection: resolved by the two-emitter fit into two rows
    of one ``pair``, each near its own spot, or flagged ``unresolved``; only pairs closer than
    RESOLVED_PX may be neither, and then the one row is one emitter of both spots' photons at
    their midpoint (within 0.05 px: its Cramér–Rao bound is ~0.006 px; photons 2.0x one spot's
    within 5 %), not a position pulled anywhere else."""
    frames, truth, locs, _ = dense
    one_spot = 2 * np.pi * SIGMA**2 * AMPLITUDE
    counts = {"split": 0, "flagged": 0, "midpoint": 0}
    for t in range(N_FRAMES):
        for frame, spots, separation, rows in merged_pairs(locs, truth, t):
            fits = frame.loc[rows]
            if rows[0] != rows[1] and fits["pair"].iloc[0] >= 0 and fits["pair"].nunique() == 1:
                # each spot within 5 of its row's own standard errors (a normal error passes
                # 5 σ once in 10^6)
                error = fits[["x", "y"]].to_numpy() - truth[t][list(spots)]
                assert np.all(np.abs(error) <= 5 * fits[["x_err", "y_err"]].to_numpy()), fits
                counts["split"] += 1
            elif fits["unresolved"].all():
                counts["flagged"] += 1
            else:
                assert separation < RESOLVED_PX, (separation, fits)
                fit = fits.iloc[0]
                midpoint = truth[t][list(spots)].mean(axis=0)
                assert np.hypot(fit["x"] - midpoint[0], fit["y"] - midpoint[1]) <= 0.05, fit
                assert fit["photons"] / one_spot == pytest.approx(2.0, rel=0.05), fit
                counts["midpoint"] += 1
    # the cases this test is about occur in this sample (8 split, 5 closer than 2.3 px here)
    assert counts["split"] >= 5 and sum(counts.values()) >= 10, counts

"""`localize` takes a detected neighbour's light out of a spot's ROI before its final fit,
against the geometry that drew the frames.

Each frame holds pairs of round Gaussian spots (eq. 1 at pixel centres, σ = 1.3 px, 3,000 and
6,000 photons over 10 photons/px, Poisson noise), 7 px apart along x: the bright one lies inside
the dim one's 11 px ROI, but far enough away that detection finds both and no two-emitter fit
is needed. The truth is where each spot was drawn.
"""

import numpy as np
import pytest

from latentz.localization import localize
from latentz.localization.neighbours import neighbour_light

SIGMA, BACKGROUND, APART = 1.3, 10.0, 7.0
DIM, BRIGHT = 3000.0, 6000.0
SIZE, STEP = 96, 24


def gaussian(shape, x, y, photons, sigma=SIGMA):
    """Round eq. 1 at the pixel centres (pixel [i, j] at x = j, y = i)."""
    rows, cols = np.indices(shape, dtype=float)
    peak = photons / (2 * np.pi * sigma**2)
    return peak * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * sigma**2))


def pair_frames(
    rng: np.random.Generator, n_frames: int, dim: float, bright: float
) -> tuple[np.ndarray, list[tuple[int, float, float]], list[tuple[int, float, float]]]:
    """``n_frames`` Poisson frames of dim spots (photons ``dim``) each ``APART`` px left of a
    bright one (``bright``), two columns of them every ``STEP`` px; and the (frame, x, y) of
    each dim and each bright spot."""
    frames, dims, brights = [], [], []
    for t in range(n_frames):
        image = np.full((SIZE, SIZE), BACKGROUND)
        for cy in range(STEP // 2, SIZE, STEP):
            for cx in (20.0, 64.0):
                x, y = cx + rng.uniform(-0.5, 0.5), cy + rng.uniform(-0.5, 0.5)
                image += gaussian(image.shape, x, y, dim)
                image += gaussian(image.shape, x + APART, y, bright)
                dims.append((t, x, y))
                brights.append((t, x + APART, y))
        frames.append(rng.poisson(image))
    return np.stack(frames).astype(float), dims, brights


@pytest.fixture(scope="module")
def frames_and_dim_spots():
    frames, dim, _ = pair_frames(np.random.default_rng(3), 12, DIM, BRIGHT)
    return frames, np.array(dim)


def test_a_dim_spot_beside_a_bright_one_is_unbiased_and_its_error_holds(frames_and_dim_spots):
    """The dim spots' mean x error lies within 3 standard errors of zero (one fit without the
    neighbour's light taken out is pulled towards it), and their reported x error covers
    68 % of the errors within 2 binomial standard errors."""
    frames, dim = frames_and_dim_spots
    locs = localize(frames, pairs=False)
    errors, sigmas = [], []
    for t, x, y in dim:
        rows = locs[locs["frame"] == t]
        nearest = np.argmin(np.hypot(rows["x"] - x, rows["y"] - y))
        assert np.hypot(rows["x"].iloc[nearest] - x, rows["y"].iloc[nearest] - y) < 1.0
        errors.append(rows["x"].iloc[nearest] - x)
        sigmas.append(rows["x_err"].iloc[nearest])
    errors, sigmas = np.array(errors), np.array(sigmas)
    assert abs(errors.mean()) <= 3 * errors.std() / np.sqrt(errors.size), errors.mean()
    covered = np.mean(np.abs(errors) <= sigmas)
    assert abs(covered - 0.683) <= 2 * np.sqrt(0.683 * 0.317 / errors.size), covered


def test_neighbour_light_is_the_other_spots_image_inside_the_roi():
    """Two fits 5 px apart in one frame and a third in another frame: each 11 px ROI receives
    the other's Gaussian of the same frame, and nothing of its own or of the other frame."""
    params = np.array([[20.0, 20.0, 100.0, 5.0, 1.3, 1.3, 0.0],
                       [25.0, 21.0, 300.0, 5.0, 1.5, 1.2, 0.0],
                       [20.0, 20.0, 100.0, 5.0, 1.3, 1.3, 0.0]])  # fmt: skip
    frame = np.array([0, 0, 1])
    corner = np.array([[15, 15], [20, 16], [15, 15]])
    light = neighbour_light(params, frame, corner, (11, 11))
    rows, cols = np.indices((11, 11), dtype=float)
    u, v = (cols + 15 - 25.0) / 1.5, (rows + 15 - 21.0) / 1.2
    np.testing.assert_allclose(light[0], 300.0 * np.exp(-0.5 * (u**2 + v**2)), rtol=1e-12)
    u, v = (cols + 20 - 20.0) / 1.3, (rows + 16 - 20.0) / 1.3
    np.testing.assert_allclose(light[1], 100.0 * np.exp(-0.5 * (u**2 + v**2)), rtol=1e-12)
    assert not light[2].any()


def test_a_roi_receives_the_sum_of_all_its_neighbours_light():
    """Three fits around a fourth, each within reach of its 11 px ROI (9 px off in x and in y:
    REACH_PX = 4 beyond the ROI's half width) and 18 px from each other: the centre's ROI
    receives the three Gaussians summed, each other ROI the centre's alone."""
    centre = [50.0, 50.0, 200.0, 5.0, 1.4, 1.4, 0.0]
    outer = [[59.0, 41.0, 100.0], [41.0, 41.0, 300.0], [50.0, 59.0, 50.0]]
    params = np.array([centre] + [[x, y, a, 5.0, 1.2, 1.2, 0.0] for x, y, a in outer])
    corner = params[:, :2] - 5
    light = neighbour_light(params, np.zeros(4, int), corner, (11, 11))
    rows, cols = np.indices((11, 11), dtype=float)

    def gaussian(k: int, into: int) -> np.ndarray:
        """Fit k's Gaussian, without its background, on the pixels of ROI ``into``."""
        x, y, amplitude, _, wx, wy, _ = params[k]
        u, v = (cols + corner[into, 0] - x) / wx, (rows + corner[into, 1] - y) / wy
        return amplitude * np.exp(-0.5 * (u**2 + v**2))

    np.testing.assert_allclose(light[0], sum(gaussian(k, 0) for k in (1, 2, 3)), rtol=1e-12)
    for k in (1, 2, 3):
        np.testing.assert_allclose(light[k], gaussian(0, k), rtol=1e-12)


def test_a_dim_spot_with_a_brighter_neighbour_inside_its_roi_is_fitted_where_it_lies():
    """A 1,000-photon spot 7 px from a 5,000-photon one, both detected, in 15 px ROIs: each ROI
    holds the other spot's core. The dim spot's fit starts at its detection's maximum, so at
    least 80 % converge on the dim spot (88 %: the start's widths, from the whole ROI's moments,
    take in the neighbour's light, and the rest slide to it); a start at the ROI's brightest box
    put every one of them on its bright neighbour, a duplicate of that neighbour's fit."""
    frames, dims, brights = pair_frames(np.random.default_rng(5), 6, 1000.0, 5000.0)
    locs = localize(frames, roi_size=15, pairs=False)
    kept = locs[locs["converged"] & ~locs["duplicate"]]
    dim, bright = (np.array([np.hypot(rows["x"] - x, rows["y"] - y).min()
                             for t, x, y in spots for rows in [kept[kept["frame"] == t]]])
                   for spots in (dims, brights))  # fmt: skip
    assert np.all(bright < 0.5), bright.max()
    assert np.mean(dim < 0.5) >= 0.8, np.sort(dim)[-10:]

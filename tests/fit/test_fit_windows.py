"""fit_arrays with per-ROI windows: the pixels outside a ROI's window are left out of the fit.

Truth is where the spots were rendered (eq. 1 with Poisson noise, `fit_truth`): a spot's centre
lies 0–5 px inside the clipped edge of its window, as an emitter 0–5 px from the frame's edge
lies inside the frame."""

import numpy as np
import pytest
from fit_truth import noisy_rois, truth_table

from latentz.fit import PARAMS, crlb, fit_arrays, fit_rois

SIZE = 11
CENTRE = SIZE // 2


def _edge_spots(n, seed, photons=(2e3, 2e3)):
    """``n`` spots at the ROI centre (±0.5 px), and windows that clip the columns left of the
    centre so that the spot's centre lies ``d`` = 0–5 px inside the window (as many of each)."""
    table = truth_table(n, SIZE, seed=seed, photons=photons, background=(20.0, 20.0), wmax=1.6)
    rois = noisy_rois(table, SIZE, seed=seed + 1)
    d = np.arange(n) % 6
    windows = np.column_stack([np.zeros(n), np.full(n, SIZE), CENTRE - d, np.full(n, SIZE)])
    return table, rois, windows.astype(int), d


def test_whole_windows_give_the_fits_without_windows_bit_for_bit():
    table, rois, windows, _ = _edge_spots(120, seed=3)
    whole = np.arange(120) % 3 == 0
    windows[whole] = [0, SIZE, 0, SIZE]
    with_windows = fit_arrays(rois, windows=windows, errors="sandwich")
    without = fit_arrays(rois[whole], errors="sandwich")
    for a, b in zip(with_windows, without, strict=True):
        np.testing.assert_array_equal(np.asarray(a)[whole], np.asarray(b))


def test_pixels_outside_the_window_are_not_seen():
    table, rois, windows, _ = _edge_spots(60, seed=5)
    columns = np.arange(SIZE)[None, None, :]
    outside = columns < windows[:, 2, None, None]
    blank, bright = rois.copy(), rois.copy()
    blank[np.broadcast_to(outside, rois.shape)] = np.nan
    bright[np.broadcast_to(outside, rois.shape)] = 1e6
    a = fit_arrays(blank, windows=windows, errors="sandwich")
    b = fit_arrays(bright, windows=windows, errors="sandwich")
    assert a.converged.mean() > 0.95
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    # the table API passes the windows on; x, y stay in the whole ROI's pixels
    table_fit = fit_rois(blank, windows=windows)
    np.testing.assert_array_equal(table_fit[["x", "y"]].to_numpy(), a.params[:, :2])
    assert np.all(np.abs(a.params[a.converged, 0] - table.x[a.converged]) < 1.0)


def test_clipped_fits_hold_their_bounds_and_the_bounds_grow_as_fewer_pixels_are_seen():
    n = 3000
    table, rois, windows, d = _edge_spots(n, seed=7)
    fit = fit_arrays(rois, windows=windows)
    ok = fit.converged
    assert ok.mean() > 0.99
    truth = table[list(PARAMS)].to_numpy()
    # the bound of the truth in each window's pixels: the fit's reported error is the bound at
    # its estimate, within a few per cent of the truth's
    inside = truth.copy()
    bound = np.empty(n)
    for k in range(6):
        rows = d == k
        inside[rows, 0] -= CENTRE - k
        bound[rows] = crlb(inside[rows], shape=(SIZE, SIZE - (CENTRE - k)))[:, 0]
    np.testing.assert_allclose(np.median(fit.errors[ok, 0] / bound[ok]), 1.0, atol=0.05)
    # one spot's bound as its window is clipped closer to its centre: it grows as fewer
    # pixels are seen, to far above the whole ROI's where half the spot is cut off
    spot = np.repeat(truth[:50], 6, axis=0)
    spot[:, 0] -= np.tile(CENTRE - np.arange(6), 50)
    grown = np.array([crlb(spot[k::6], shape=(SIZE, SIZE - CENTRE + k))[:, 0] for k in range(6)])
    whole = crlb(truth[:50], shape=SIZE)[:, 0]
    assert np.all(np.diff(grown, axis=0) <= 1e-12) and np.all(grown[-1] >= whole * (1 - 1e-12))
    assert np.all(grown[0] > 1.5 * whole)
    for k in range(6):
        rows = ok & (d == k)
        for p in (0, 1):  # x across the clipped edge, y along it
            z = (fit.params[rows, p] - truth[rows, p]) / fit.errors[rows, p]
            covered = np.mean(np.abs(z) < 1)
            # ~500 fits per distance: 2.6 binomial SE of a 68.3 % share is 5.4 %
            spread = 2.6 * np.sqrt(0.683 * 0.317 / rows.sum())
            assert abs(covered - 0.683) < spread, (k, p, covered)


def test_a_window_narrower_than_3_px_is_a_failed_fit():
    table, rois, windows, _ = _edge_spots(6, seed=9)
    windows[0] = [0, SIZE, SIZE - 2, SIZE]
    fit = fit_arrays(rois, windows=windows)
    assert not fit.converged[0] and np.all(np.isnan(fit.params[0]))
    assert fit.converged[1:].all()


@pytest.mark.parametrize(
    "windows, match",
    [
        (np.zeros((5, 4), int), "Expected `windows` of shape"),
        (np.tile([0, SIZE, 4, 3], (6, 1)), "non-empty range"),
        (np.tile([0, SIZE + 1, 0, SIZE], (6, 1)), "within 0..11"),
    ],
)
def test_bad_windows_are_refused_clearly(windows, match):
    rois = noisy_rois(truth_table(6, SIZE, seed=1), SIZE, seed=2)
    with pytest.raises(ValueError, match=match):
        fit_arrays(rois, windows=windows)


def test_clipped_fits_match_the_numpy_twin_on_the_windows_pixels():
    """The NumPy twin fits a window's pixels as a ROI of their own; the kernels' clipped fits,
    moved back into the window's pixels, are the same fits."""
    from latentz.fit._reference import fit_reference
    from latentz.fit.api import METHODS, parameter_bounds

    _, rois, windows, d = _edge_spots(24, seed=11)
    got = fit_arrays(rois, windows=windows)
    for k in range(6):
        rows = np.flatnonzero(d == k)
        c0 = CENTRE - k
        pixels = rois[rows, :, c0:]
        lower, upper = parameter_bounds(pixels.shape[1:], 0.0)
        want = fit_reference(pixels, method=METHODS["mle"], s2=0.0, lower=lower, upper=upper)
        params = got.params[rows].copy()
        params[:, 0] -= c0
        np.testing.assert_allclose(params, want[0], rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(got.errors[rows], want[1], rtol=1e-8, atol=1e-8)

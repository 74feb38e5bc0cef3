"""Determinism: the same inputs and seed give bit-identical outputs across runs, across 1 or 2
numba threads and across the dask "threads" and "synchronous" schedulers."""

import numba
import numpy as np
import pandas as pd
import pytest

from latentz.calibration import calibrate
from latentz.fit import fit_rois
from latentz.localization import localize
from latentz.motion import motion_uncertainty

pytestmark = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="numba was started with fewer than 2 threads"
)


def with_threads(n, func, *args, **kwargs):
    before = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        return func(*args, **kwargs)
    finally:
        numba.set_num_threads(before)


def assert_identical(a, b):
    pd.testing.assert_frame_equal(a, b, check_exact=True)


@pytest.fixture(scope="module")
def movie(small_microscope):
    return small_microscope.gear.frames[:3]


def test_localize_is_bit_identical_across_threads_and_schedulers(movie):
    # chunk_frames=1 makes "threads" run three chunks at once on two cores
    first = with_threads(1, localize, movie, scheduler="synchronous", chunk_frames=1)
    assert len(first) > 10
    for threads in (1, 2):
        for scheduler in ("synchronous", "threads"):
            again = with_threads(threads, localize, movie, scheduler=scheduler, chunk_frames=1)
            assert_identical(first, again)


def test_fit_rois_is_bit_identical_across_threads(movie):
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:11, :11]
    # 700 ROIs so the parallel kernel splits them into several chunks
    x0, y0 = rng.uniform(4, 6, (2, 700, 1, 1))
    mu = 100 + 2000 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * 1.6**2))
    rois = rng.poisson(mu).astype(np.float64)
    tables = [with_threads(n, fit_rois, rois) for n in (1, 2, 1, 2)]
    assert tables[0]["converged"].all()
    for table in tables[1:]:
        assert_identical(tables[0], table)


def test_motion_uncertainty_is_bit_identical_across_threads(small_microscope):
    truth = small_microscope.gear.truth
    tracks = truth.loc[truth["in_frame"], ["frame", "particle", "x_nm", "y_nm", "z_nm"]].copy()
    noise = np.random.default_rng(5).normal(0, [1.0, 1.0, 10.0], (len(tracks), 3))
    tracks[["x_nm", "y_nm", "z_nm"]] += noise
    runs = [with_threads(n, motion_uncertainty, tracks, n_sim=300, seed=7) for n in (1, 2, 2)]
    for table in runs[1:]:
        assert_identical(runs[0], table)
    other_seed = motion_uncertainty(tracks, n_sim=300, seed=8)
    assert not other_seed["sigma"].equals(runs[0]["sigma"])  # the seed does matter


def test_calibrate_nearest_and_apply_are_bit_identical(small_microscope, movie):
    data = small_microscope.calibration
    stack = data.stacks[0]
    spots = localize(movie, roi_size=15, scheduler="synchronous")
    results = []
    for threads in (1, 2):
        cal = with_threads(threads, calibrate, stack, data.z_nm, field_model="nearest", roi_size=15)
        results.append((cal, with_threads(threads, cal.apply, spots)))
    (cal1, z1), (cal2, z2) = results
    assert_identical(z1, z2)
    assert z1["z_nm"].notna().mean() > 0.5
    assert_identical(cal1.scores, cal2.scores)

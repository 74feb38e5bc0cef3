"""Global-shutter imaging frequency and its trade-off with centroid precision (Supp. Fig. 22)."""

import numpy as np
import pytest

import latentz as lz
from latentz.camera.readout import constellation_precision_nm, frame_rate_hz, readout_figure


def test_the_papers_rate_at_1_ms_and_the_full_sensor():
    # the paper: 1 ms exposure + 10 ms readout of 2048 rows (1024 row pairs) -> 90.9 Hz
    assert lz.frame_rate_hz(exposure_ms=1.0, n_rows=2048) == pytest.approx(1e3 / 11.0)
    assert round(lz.frame_rate_hz(exposure_ms=1.0, n_rows=2048), 1) == 90.9
    # the rounded 10 µs per row pair gives 1 / 11.24 ms
    assert frame_rate_hz(1.0, 2048, row_pair_us=10.0) == pytest.approx(1e3 / 11.24)


def test_fewer_rows_image_faster_up_to_the_exposure_limit():
    rows = np.array([2048, 1024, 256, 2])
    rate = frame_rate_hz(1.0, rows, row_pair_us=10.0)
    np.testing.assert_allclose(rate, 1e3 / (1.0 + rows / 2 * 0.01))
    assert np.all(np.diff(rate) > 0) and rate[-1] < 1e3  # never beyond 1 / exposure


def test_precision_follows_the_photons_collected():
    # a quarter of the rows for the same exposure collects a quarter of the photons: 2x worse
    full = constellation_precision_nm(1.0, 2048, photons_per_ms=1e6, psf_sigma_nm=300.0)
    quarter = constellation_precision_nm(1.0, 512, photons_per_ms=1e6, psf_sigma_nm=300.0)
    assert full == pytest.approx(300.0 / 1e3)
    assert quarter == pytest.approx(2 * full)


@pytest.mark.parametrize(
    "args, match",
    [((0.0, 2048), "exposure_ms"), ((1.0, -2), "n_rows"), ((np.nan, 2048), "exposure_ms")],
)
def test_bad_input_names_the_parameter(args, match):
    with pytest.raises(ValueError, match=match):
        frame_rate_hz(*args)


def test_the_figure_has_both_panels():
    import matplotlib

    matplotlib.use("Agg")
    fig = readout_figure()
    rate_ax, precision_ax = fig.axes
    assert len(rate_ax.lines) == len(precision_ax.lines) == 6  # 5 readout extents + the dot
    assert rate_ax.lines[-1].get_ydata()[0] == pytest.approx(1e3 / 11.0)

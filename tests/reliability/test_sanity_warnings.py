"""Each physical sanity check warns, naming the value and the expected range; sane input
is silent."""

import warnings

import numpy as np
import pytest

from latentz._shared.sanity import (
    LatentzWarning,
    check_offset,
    check_pixel_size,
    check_widths,
    check_z_step,
)


def silent(func, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        func(*args, **kwargs)


def test_offset_above_median_warns():
    with pytest.warns(LatentzWarning, match=r"offset 500 ADU.*median 100 ADU.*<= 100"):
        check_offset(500.0, 100.0)
    silent(check_offset, 100.0, 120.0)


def test_pixel_size_mismatch_warns():
    with pytest.warns(LatentzWarning, match=r"Pixel size 65 nm.*108 nm; expected 106.92..109.08"):
        check_pixel_size(65.0, 108.0)
    silent(check_pixel_size, 108.0, 108.0)


def test_z_step_that_the_widths_contradict_warns():
    # d / sigma0^2 = 0.0121 per nm on latentz's simulator (NA 0.55 in air, 1 µm particles):
    # a step given in µm (0.05) for nm (50) makes it 1000x smaller, one 10x too large 10x larger
    with pytest.warns(LatentzWarning, match=r"z step 0.05 nm .* 1.21e-05 σ0² .* 13.8..263 nm"):
        check_z_step(0.05, 0.0121e-3)
    with pytest.warns(LatentzWarning, match=r"z step 500 nm .* 0.121 σ0²"):
        check_z_step(500.0, 0.121)
    with pytest.warns(LatentzWarning, match=r"z step 1 nm .* 0.0009 σ0²"):
        check_z_step(1.0, 0.0009)  # the SMLM 2016 beads with a step 10x too small
    silent(check_z_step, 50.0, 0.0121)  # NA 0.55 in air, 1 µm particles
    silent(check_z_step, 10.0, 0.0090)  # SMLM 2016 beads (the lowest measured)
    silent(check_z_step, 10.0, 0.0170)  # fit3Dcspline bead, 100 nm pixels (the highest)
    silent(check_z_step, 10.0, float("nan"))  # nothing to judge by


def test_calibrate_warns_about_a_z_step_in_the_wrong_unit(small_microscope):
    from latentz.calibration import calibrate

    data = small_microscope.calibration
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        calibrate(list(data.stacks), data.z_nm, camera=data.camera, field_model="nearest")
    with pytest.warns(LatentzWarning, match=r"z step 0.1 nm makes the spot widths' depth of focus"):
        try:
            calibrate(
                list(data.stacks), data.z_nm / 1000, camera=data.camera, field_model="nearest"
            )
        except ValueError:
            pass  # with every z a thousand times too small, later stages may give up too


def _localize_args(small_microscope, calibration_file, out):
    movie = str(small_microscope.folder / "movie.tif")
    return ["localize", movie, "--calibration", str(calibration_file), "--quiet", "--out", str(out)]


def test_localize_warns_about_a_pixel_size_unlike_the_calibrations(
    small_microscope, calibration_file, tmp_path
):
    from click.testing import CliRunner

    from latentz.cli import main

    out = tmp_path / "locs.parquet"
    args = _localize_args(small_microscope, calibration_file, out)
    with pytest.warns(LatentzWarning, match=r"Pixel size 65 nm is inconsistent .* 130 nm"):
        result = CliRunner().invoke(main, [*args, "--pixel-size-nm", "65"])
    assert result.exit_code == 0 and out.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error", LatentzWarning)
        result = CliRunner().invoke(main, [*args, "--gain", "0.5"])
    assert result.exit_code == 0, result.output


def test_widths_outside_calibration_warn():
    with pytest.warns(LatentzWarning, match=r"1 spot widths \(e.g. 9 px\).*expected 0.6..5 px"):
        check_widths(np.array([1.3, 1.5, 9.0, np.nan]), (1.2, 2.5))
    silent(check_widths, np.array([1.3, 2.4, np.nan]), (1.2, 2.5))


def test_localize_warns_once_per_run_not_once_per_chunk(
    small_microscope, calibration_file, tmp_path
):
    from click.testing import CliRunner

    from latentz.cli import main

    args = _localize_args(small_microscope, calibration_file, tmp_path / "locs.parquet")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = CliRunner().invoke(main, [*args, "--chunk-frames", "1", "--offset", "60000"])
    assert result.exit_code == 0, result.output
    offsets = [w for w in caught if "Camera offset 60000 ADU" in str(w.message)]
    assert len(offsets) == 1  # the movie has several one-frame chunks

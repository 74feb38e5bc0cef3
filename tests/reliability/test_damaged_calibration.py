"""A damaged calibration file, or one from another latentz format, gives one clear CLI error line
and exit status 2, and no output."""

import json
import shutil

import h5py
import pytest
from click.testing import CliRunner

from latentz.cli import main


def _localize_with(cal_path, small_microscope, tmp_path):
    out = tmp_path / "locs.parquet"
    result = CliRunner().invoke(
        main,
        [
            "localize",
            str(small_microscope.folder / "movie.tif"),
            "--calibration",
            str(cal_path),
            "--quiet",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("latentz: error:"), result.output
    assert not out.exists()
    return lines[0]


def test_missing_dataset(calibration_file, small_microscope, tmp_path):
    bad = tmp_path / "bad.h5"
    shutil.copy(calibration_file, bad)
    with h5py.File(bad, "a") as handle:
        del handle["culling/culled"]
    assert "damaged latentz calibration" in _localize_with(bad, small_microscope, tmp_path)


def test_other_format_version(calibration_file, small_microscope, tmp_path):
    bad = tmp_path / "future.h5"
    shutil.copy(calibration_file, bad)
    with h5py.File(bad, "a") as handle:
        handle.attrs["format"] = json.dumps("latentz-calibration/99")
        handle.attrs["version"] = json.dumps("9.0.0")
    line = _localize_with(bad, small_microscope, tmp_path)
    assert "latentz-calibration/99" in line and "9.0.0" in line


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_file(calibration_file, small_microscope, tmp_path, fraction):
    data = calibration_file.read_bytes()
    bad = tmp_path / "cut.h5"
    bad.write_bytes(data[: int(len(data) * fraction)])
    assert "Cannot read cut.h5" in _localize_with(bad, small_microscope, tmp_path)


def test_not_hdf5(small_microscope, tmp_path):
    bad = tmp_path / "text.h5"
    bad.write_text("not a calibration")
    assert "Cannot read text.h5" in _localize_with(bad, small_microscope, tmp_path)

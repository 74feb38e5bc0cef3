"""Damaged input files give one clear `latentz: error:` line, exit status 2, and no output."""

import numpy as np
import pandas as pd
import pytest
import tifffile
from click.testing import CliRunner

from latentz.cli import main


def one_error_line(args, match):
    result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert lines[0].startswith("latentz: error:"), lines[0]
    assert match in lines[0], lines[0]


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9])
def test_truncated_tiff(tmp_path, keep):
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, np.full((6, 32, 32), 100, np.uint16), photometric="minisblack")
    data = whole.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: int(keep * len(data))])
    out = tmp_path / "calibration.h5"
    args = ["calibrate", cut, "--z-start", 0, "--z-step", 100, "--out", out]
    one_error_line(args, "cut.tif")
    assert not out.exists()


@pytest.mark.parametrize(
    ("table", "match"),
    [
        (pd.DataFrame({"frame": [0, 1], "x_nm": [1.0, 2.0]}), "missing column"),
        (pd.DataFrame({"a": []}), "missing column"),
    ],
)
def test_parquet_with_missing_columns(tmp_path, table, match):
    locs = tmp_path / "locs.parquet"
    table.to_parquet(locs)
    out = tmp_path / "motion.csv"
    one_error_line(["track", locs, "--out", out, "--quiet"], match)
    assert not out.exists()

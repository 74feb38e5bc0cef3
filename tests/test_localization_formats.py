"""Localization files in other programs' formats: ThunderSTORM CSV written and read back, a file
in ThunderSTORM's documented layout read, Picasso HDF5 read back; and the commands that take
any of them (render, drift, frc)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from latentz.io import read_localizations
from latentz.io.picasso import write_picasso
from latentz.io.thunderstorm import THUNDERSTORM_COLUMNS, write_thunderstorm

PIXEL_NM = 110.0


def _locs(n: int = 400, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(5, 60, n), rng.uniform(5, 60, n)
    table = pd.DataFrame(
        {
            "frame": np.sort(rng.integers(0, 2000, n)),
            "x": x,
            "y": y,
            "photons": rng.uniform(1e3, 1e4, n),
            "background": rng.uniform(5, 20, n),
            "wx": rng.uniform(1, 2, n),
            "wy": rng.uniform(1, 2, n),
            "x_err": rng.uniform(0.05, 0.1, n),
            "y_err": rng.uniform(0.05, 0.1, n),
            "x_nm": x * PIXEL_NM,
            "y_nm": y * PIXEL_NM,
            "z_nm": rng.uniform(-400, 400, n),
            "x_err_nm": rng.uniform(5, 10, n),
            "y_err_nm": rng.uniform(5, 10, n),
            "z_err_nm": rng.uniform(15, 30, n),
            "in_range": True,
        }
    )
    table.loc[3, ["z_nm", "z_err_nm", "in_range"]] = [np.nan, np.nan, False]
    return table


def test_thunderstorm_round_trip_through_pandas(tmp_path):
    """ThunderSTORM's column names in its order, its units (nm, photons, frames from 1), and
    read back to latentz's columns to the 6 significant digits written."""
    locs = _locs()
    path = write_thunderstorm(locs, tmp_path / "locs.csv", pixel_size_nm=PIXEL_NM)
    raw = pd.read_csv(path)
    assert tuple(raw.columns) == THUNDERSTORM_COLUMNS
    assert path.read_text().splitlines()[0].startswith('"id","frame","x [nm]"')
    np.testing.assert_array_equal(raw["frame"], locs["frame"] + 1)
    np.testing.assert_allclose(raw["sigma1 [nm]"], locs["wx"] * PIXEL_NM, rtol=1e-5)
    np.testing.assert_allclose(raw["intensity [photon]"], locs["photons"], rtol=1e-5)
    assert np.isnan(raw.loc[3, "z [nm]"])
    back, meta = read_localizations(path)
    assert meta["format"] == "thunderstorm"
    np.testing.assert_array_equal(back["frame"], locs["frame"])
    for column in ("x_nm", "y_nm", "z_nm", "z_err_nm", "photons", "background"):
        np.testing.assert_allclose(back[column], locs[column], rtol=1e-5, err_msg=column)
    lateral = (locs["x_err_nm"] + locs["y_err_nm"]) / 2
    np.testing.assert_allclose(back["x_err_nm"], lateral, rtol=1e-5)
    np.testing.assert_array_equal(back["in_range"], locs["in_range"])


def test_a_file_in_thunderstorms_documented_2d_layout_is_read(tmp_path):
    """A 2D export as ThunderSTORM writes it (quoted headers, "sigma [nm]", "chi2",
    "uncertainty_xy [nm]", frames from 1): its numbers come back in latentz's columns."""
    path = tmp_path / "ts.csv"
    path.write_text(
        '"id","frame","x [nm]","y [nm]","sigma [nm]","intensity [photon]","offset [photon]",'
        '"bkgstd [photon]","chi2","uncertainty_xy [nm]"\n'
        "1.0,1.0,5103.2,2210.5,131.9,2315.0,41.2,7.1,812.5,9.8\n"
        "2.0,3.0,880.0,10450.25,140.0,1200.5,39.0,6.9,700.0,14.2\n"
    )
    table, meta = read_localizations(path)
    assert meta["format"] == "thunderstorm"
    assert table["frame"].tolist() == [0, 2]
    assert table["x_nm"].tolist() == [5103.2, 880.0]
    assert table["y_nm"].tolist() == [2210.5, 10450.25]
    assert table["x_err_nm"].tolist() == table["y_err_nm"].tolist() == [9.8, 14.2]
    assert table["sigma1_nm"].tolist() == [131.9, 140.0]
    assert table["photons"].tolist() == [2315.0, 1200.5]
    assert table["z_nm"].isna().all() and not table["in_range"].any()


def test_picasso_file_reads_back_in_nm(tmp_path):
    locs = _locs()
    h5, _ = write_picasso(
        locs, tmp_path / "locs.hdf5", width=64, height=64, n_frames=2000, pixel_size_nm=PIXEL_NM
    )
    back, meta = read_localizations(h5)
    assert meta["format"] == "picasso"
    np.testing.assert_allclose(back["x_nm"], locs["x"] * PIXEL_NM, rtol=1e-6)
    np.testing.assert_allclose(back["x_err_nm"], locs["x_err"] * PIXEL_NM, rtol=1e-6)
    np.testing.assert_allclose(back["z_nm"], locs["z_nm"], rtol=1e-6)
    with pytest.raises(ValueError, match="Cannot tell the format"):
        read_localizations(h5.with_suffix(".yaml"))


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "latentz.cli", *args], capture_output=True, text=True
    )


def test_render_drift_and_frc_commands_read_thunderstorm(tmp_path):
    locs = _locs(n=3000, seed=1)
    source = write_thunderstorm(locs, tmp_path / "ts.csv", pixel_size_nm=PIXEL_NM)
    out = _cli("render", str(source), "--out", str(tmp_path / "image.png"), "--pixel-nm", "50")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "image.png").stat().st_size > 0
    out = _cli("render", str(source), "--out", str(tmp_path / "image.tif"), "--pixel-nm", "50")
    assert out.returncode == 0, out.stderr
    out = _cli(
        "drift", str(source), "--out", str(tmp_path / "fixed.parquet"), "--segment-frames", "500"
    )
    assert out.returncode == 0, out.stderr
    fixed = pd.read_parquet(tmp_path / "fixed.parquet")
    assert {"drift_x_nm", "drift_y_nm", "drift_z_nm"} <= set(fixed.columns)
    assert (tmp_path / "fixed.drift.png").exists()
    out = _cli("frc", str(source), "--pixel-nm", "20", "--out", str(tmp_path / "frc.png"))
    assert out.returncode == 0, out.stderr
    assert "FRC resolution" in out.stdout and (tmp_path / "frc.png").exists()


def test_commands_say_one_line_for_bad_input(tmp_path):
    bad = tmp_path / "notes.txt"
    bad.write_text("hello")
    out = _cli("render", str(bad), "--out", str(tmp_path / "image.png"))
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
    assert "Cannot tell the format" in out.stderr
    assert not (tmp_path / "image.png").exists()
    source = write_thunderstorm(_locs(), tmp_path / "ts.csv", pixel_size_nm=PIXEL_NM)
    out = _cli("render", str(source), "--out", str(tmp_path / "image.jpg"))
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr

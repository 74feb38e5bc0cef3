"""Table 1's drift column from a separate recording without intentional motion (Supp. Note 2),
through the track pipeline and `latentz track --static`."""

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from latentz.cli import main
from latentz.cli.steps import track_tables
from latentz.io import read_table, write_table
from latentz.simulate.gear_motion import gear_trajectory

DRIFT_NM = np.array([3.0, -2.0, 10.0])  # per frame, steady
NOISE_NM = np.array([2.0, 2.0, 80.0])
N_PARTICLES, N_FRAMES = 20, 30


def _static_locs(seed=0):
    """Unlinked localizations of a still constellation drifting by DRIFT_NM per frame."""
    rng = np.random.default_rng(seed)
    body = rng.uniform(-1e5, 1e5, (N_PARTICLES, 3))
    frames = np.repeat(np.arange(N_FRAMES), N_PARTICLES)
    pos = np.tile(body, (N_FRAMES, 1)) + frames[:, None] * DRIFT_NM
    pos += rng.normal(0.0, NOISE_NM, pos.shape)
    table = pd.DataFrame(pos, columns=["x_nm", "y_nm", "z_nm"]).assign(frame=frames, in_range=True)
    return table.sample(frac=1.0, random_state=seed)


def _moving_locs():
    locs = gear_trajectory(8, n_particles=12, seed=2).positions
    return locs.drop(columns="particle").assign(in_range=True)


def _expected_and_tolerance():
    # each frame pair's mean displacement is DRIFT + e, e ~ N(0, 2 NOISE² / N) per axis; the
    # RMS over the pairs has standard error ~ sqrt((4 d² s² + 2 s⁴) / n_pairs) / (2 rms)
    s2 = 2 * NOISE_NM**2 / N_PARTICLES
    rms = np.sqrt(DRIFT_NM**2 + s2)
    se = np.sqrt((4 * DRIFT_NM**2 * s2 + 2 * s2**2) / (N_FRAMES - 1)) / (2 * rms)
    return rms, 4 * se


def test_static_locs_fill_the_drift_column():
    tables = track_tables(_moving_locs(), static_locs=_static_locs(), n_sim=200)
    summary = tables["table1"]
    expected, tol = _expected_and_tolerance()
    got = summary.loc[["dx_nm", "dy_nm", "dz_nm"], "drift"].to_numpy()
    np.testing.assert_array_less(np.abs(got - expected), tol)
    assert summary.loc[["gamma", "beta", "alpha"], "drift"].isna().all()
    total = np.hypot(summary.loc[["dx_nm", "dy_nm", "dz_nm"], "localization"], got)
    np.testing.assert_allclose(summary.loc[["dx_nm", "dy_nm", "dz_nm"], "total"], total)
    # without static data the column stays empty
    assert track_tables(_moving_locs(), n_sim=200)["table1"]["drift"].isna().all()


def test_static_data_once_and_spanning_two_frames():
    with pytest.raises(ValueError, match="not both"):
        track_tables(_moving_locs(), static_frames=[0, 1], static_locs=_static_locs(), n_sim=10)
    one_frame = _static_locs().query("frame == 0")
    with pytest.raises(ValueError, match="at least two frames"):
        track_tables(_moving_locs(), static_locs=one_frame, n_sim=10)


def test_cli_track_static_table(tmp_path):
    write_table(_moving_locs(), tmp_path / "locs.parquet")
    write_table(_static_locs(), tmp_path / "still.csv")
    args = ["track", str(tmp_path / "locs.parquet"), "--n-sim", "200", "--quiet"]
    result = CliRunner().invoke(
        main, [*args, "--static", str(tmp_path / "still.csv"), "--out", str(tmp_path / "m.csv")]
    )
    assert result.exit_code == 0, result.output
    summary = read_table(tmp_path / "m.table1.csv")[0].set_index("dof")
    expected, tol = _expected_and_tolerance()
    got = summary.loc[["dx_nm", "dy_nm", "dz_nm"], "drift"].to_numpy()
    np.testing.assert_array_less(np.abs(got - expected), tol)
    assert read_table(tmp_path / "m.csv")[1]["inputs"]["static"][0]["name"].endswith("still.csv")


def test_cli_static_movie_needs_a_calibration(tmp_path):
    write_table(_moving_locs(), tmp_path / "locs.parquet")
    (tmp_path / "still.tif").write_bytes(b"")
    result = CliRunner().invoke(
        main,
        [
            "track",
            str(tmp_path / "locs.parquet"),
            "--static",
            str(tmp_path / "still.tif"),
            "--out",
            str(tmp_path / "m.csv"),
        ],
    )
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "latentz: error: --static still.tif is a movie: pass --calibration to localize it, "
        "or give a localization table."
    ]
    assert not (tmp_path / "m.csv").exists()

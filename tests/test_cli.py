"""The command line on real files: one clear error line for bad input, the whole pipeline on a
small simulated microscope, resume after kill -9, and a dask.distributed run."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
import tifffile
from click.testing import CliRunner

from latentz.cli import main
from latentz.io import read_table


def run(*args, **kwargs):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False, **kwargs)


def one_error_line(result, match):
    assert result.exit_code == 2, result.output
    # warnings are one line each of their own (e.g. the CPU fallback of device="auto")
    lines = [
        line
        for line in result.output.splitlines()
        if line.strip() and not line.startswith("latentz: warning: ")
    ]
    assert len(lines) == 1, result.output
    assert lines[0].startswith("latentz: error:") and match in lines[0], lines[0]
    assert "Traceback" not in result.output


def test_help_lists_every_command():
    result = run("--help")
    assert result.exit_code == 0
    for command in (
        "demo",
        "simulate",
        "calibrate",
        "localize",
        "track",
        "report",
        "render",
        "drift",
        "frc",
    ):
        assert command in result.output


def test_missing_file_is_one_clear_line(tmp_path):
    one_error_line(
        run(
            "calibrate",
            tmp_path / "none.tif",
            "--z-start",
            0,
            "--z-step",
            10,
            "--out",
            tmp_path / "c.h5",
        ),
        "No such image file",
    )
    assert not (tmp_path / "c.h5").exists()


def test_wrong_dimensions_is_one_clear_line(tmp_path):
    tifffile.imwrite(
        tmp_path / "4d.tif", np.zeros((2, 3, 8, 8), np.uint16), photometric="minisblack"
    )
    one_error_line(
        run(
            "calibrate",
            tmp_path / "4d.tif",
            "--z-start",
            0,
            "--z-step",
            10,
            "--out",
            tmp_path / "c.h5",
        ),
        "frames, rows, columns",
    )


@pytest.mark.parametrize(
    ("option", "name"), [("--gain", "gain"), ("--pixel-size-nm", "pixel_size_nm")]
)
def test_non_positive_camera_values_are_one_clear_line(tmp_path, option, name):
    tifffile.imwrite(tmp_path / "s.tif", np.zeros((21, 16, 16), np.uint16))
    one_error_line(
        run(
            "calibrate",
            tmp_path / "s.tif",
            "--z-start",
            0,
            "--z-step",
            10,
            option,
            0,
            "--out",
            tmp_path / "c.h5",
        ),
        name,
    )


def test_error_from_a_subprocess_has_no_traceback(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "latentz.cli",
            "track",
            str(tmp_path / "none.parquet"),
            "--out",
            str(tmp_path / "m.csv"),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("latentz: error:") and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_simulate_writes_stacks_truth_and_metadata(tmp_path):
    result = run("simulate", "apertures", "--out", tmp_path, "--quick", "--plot")
    assert result.exit_code == 0, result.output
    names = {p.name for p in tmp_path.iterdir()}
    assert any(n.endswith(".tif") for n in names) and any(n.endswith(".csv") for n in names)
    assert any(n.endswith(".json") for n in names) and "psf_gallery.png" in names


@pytest.fixture(scope="module")
def run_dir(small_microscope):
    return small_microscope.folder, small_microscope.gear


@pytest.fixture(scope="module")
def calibrated(run_dir):
    folder, _ = run_dir
    result = run(
        "calibrate",
        folder / "stack.tif",
        "--z-file",
        folder / "z.txt",
        "--field-model",
        "nearest",
        "--quiet",
        "--out",
        folder / "cal.h5",
    )
    assert result.exit_code == 0, result.output
    return folder / "cal.h5"


def test_calibration_records_its_inputs(run_dir, calibrated):
    import hashlib

    from latentz import __version__
    from latentz.calibration import Calibration

    folder, _ = run_dir
    record = Calibration.load(calibrated).provenance
    for role, name in (("stacks", "stack.tif"), ("z_file", "z.txt")):
        (entry,) = record["inputs"][role]
        assert entry["name"].endswith(name)
        assert entry["sha256"] == hashlib.sha256((folder / name).read_bytes()).hexdigest()
    assert record["latentz_version"] == __version__
    assert record["created"].startswith("20")  # ISO 8601 date and time, UTC


def test_pipeline_localize_track_report(run_dir, calibrated):
    folder, gear = run_dir
    result = run(
        "localize",
        folder / "movie.tif",
        "--calibration",
        calibrated,
        "--roi-size",
        15,
        "--quiet",
        "--out",
        folder / "locs.parquet",
    )
    assert result.exit_code == 0, result.output
    from latentz.camera.readout import frame_rate_hz

    rows = gear.frames.shape[1]  # the acquisition rate for the movie's rows at 1 ms
    assert f"({frame_rate_hz(1.0, rows):.1f} Hz: 1 ms exposure, {rows} rows)" in result.output
    locs, meta = read_table(folder / "locs.parquet")
    assert meta["inputs"]["calibration"][0]["sha256"]  # provenance of the calibration used
    assert locs["in_range"].mean() > 0.9
    assert set(locs["frame"]) == set(range(gear.frames.shape[0]))
    result = run(
        "track", folder / "locs.parquet", "--n-sim", 200, "--quiet", "--out", folder / "motion.csv"
    )
    assert result.exit_code == 0, result.output
    motion, _ = read_table(folder / "motion.csv")
    truth = gear.gear.motion_about(np.zeros(3))
    # gamma does not depend on the centre of rotation; 8 particles give ~1e-4 rad precision
    np.testing.assert_allclose(motion["gamma"], truth["gamma"].to_numpy(), atol=2e-3)
    # a still movie (the first frame three times, localized with the calibration) for the drift
    still = folder / "still.tif"
    tifffile.imwrite(
        still,
        np.repeat(tifffile.imread(folder / "movie.tif")[:1], 3, axis=0),
        photometric="minisblack",
    )
    result = run(
        "track",
        folder / "locs.parquet",
        "--static",
        still,
        "--calibration",
        calibrated,
        "--n-sim",
        200,
        "--quiet",
        "--out",
        folder / "motion-still.csv",
    )
    assert result.exit_code == 0, result.output
    summary = read_table(folder / "motion-still.table1.csv")[0].set_index("dof")
    # identical frames: no apparent translation at all
    assert (summary.loc[["dx_nm", "dy_nm", "dz_nm"], "drift"] == 0).all()
    result = run("report", folder, "--out", folder / "report.html")
    assert result.exit_code == 0, result.output
    page = (folder / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 5 and "Table 1" in page


def test_picasso_format(run_dir, calibrated):
    folder, gear = run_dir
    result = run(
        "localize",
        folder / "movie.tif",
        "--calibration",
        calibrated,
        "--format",
        "picasso",
        "--quiet",
        "--out",
        folder / "locs.hdf5",
    )
    assert result.exit_code == 0, result.output
    import h5py
    import yaml

    with h5py.File(folder / "locs.hdf5") as handle:
        assert {"frame", "x", "y", "z", "lpx", "lpy"} <= set(handle["locs"].dtype.names)
    info = list(yaml.safe_load_all((folder / "locs.yaml").read_text()))
    assert info[0]["Frames"] == gear.frames.shape[0]


def test_thunderstorm_format_and_track_reads_it(run_dir, calibrated):
    """localize --format thunderstorm writes ThunderSTORM's columns; track reads that file and
    measures the gear's rotation as from latentz's own table (gamma within 2 mrad of truth)."""
    from latentz.io.thunderstorm import THUNDERSTORM_COLUMNS

    folder, gear = run_dir
    target = folder / "ts.csv"
    result = run(
        "localize", folder / "movie.tif", "--calibration", calibrated, "--roi-size", 15,
        "--format", "thunderstorm", "--quiet", "--out", target,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    table = pd.read_csv(target)
    assert tuple(table.columns) == THUNDERSTORM_COLUMNS
    assert set(table["frame"]) == set(range(1, gear.frames.shape[0] + 1))
    assert not list(folder.glob("ts.latentz.parquet"))
    result = run("track", target, "--n-sim", 200, "--quiet", "--out", folder / "ts-motion.csv")
    assert result.exit_code == 0, result.output
    motion, _ = read_table(folder / "ts-motion.csv")
    truth = gear.gear.motion_about(np.zeros(3))
    np.testing.assert_allclose(motion["gamma"], truth["gamma"].to_numpy(), atol=2e-3)


def test_kill_9_then_resume(run_dir, calibrated, tmp_path):
    folder, _ = run_dir
    movie = tmp_path / "long.tif"
    frames = tifffile.imread(folder / "movie.tif")
    tifffile.imwrite(movie, np.concatenate([frames] * 4))
    out = tmp_path / "locs.parquet"
    args = [
        sys.executable,
        "-m",
        "latentz.cli",
        "localize",
        str(movie),
        "--calibration",
        str(calibrated),
        "--chunk-frames",
        "2",
        "--quiet",
        "--out",
        str(out),
    ]
    proc = subprocess.Popen(args)
    chunks = tmp_path / "locs.parquet.chunks"
    deadline = time.time() + 120
    while time.time() < deadline and len(list(chunks.glob("chunk-*.parquet"))) < 2:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists()
    done = len(list(chunks.glob("chunk-*.parquet")))
    assert done >= 2
    subprocess.run(args + ["--resume"], check=True)
    resumed, _ = read_table(out)
    subprocess.run(args[:-2] + ["--out", str(tmp_path / "fresh.parquet")], check=True)
    fresh, _ = read_table(tmp_path / "fresh.parquet")
    pd.testing.assert_frame_equal(resumed, fresh)


def test_distributed_scheduler_gives_the_same_table(run_dir, calibrated, tmp_path):
    distributed = pytest.importorskip("distributed")
    folder, _ = run_dir
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    ) as cluster:
        result = run(
            "localize",
            folder / "movie.tif",
            "--calibration",
            calibrated,
            "--scheduler",
            cluster.scheduler_address,
            "--quiet",
            "--out",
            tmp_path / "dist.parquet",
        )
    assert result.exit_code == 0, result.output
    result = run(
        "localize",
        folder / "movie.tif",
        "--calibration",
        calibrated,
        "--quiet",
        "--out",
        tmp_path / "local.parquet",
    )
    dist, _ = read_table(tmp_path / "dist.parquet")
    local, _ = read_table(tmp_path / "local.parquet")
    pd.testing.assert_frame_equal(dist, local)


def test_warnings_reach_the_console_as_one_line_without_source():
    from latentz._shared.sanity import LatentzWarning
    from latentz.cli.main import _warning_line

    message = LatentzWarning("3 spot widths are far outside\nmore")
    line = _warning_line(message, LatentzWarning, "/a/b.py", 7)
    assert line == "latentz: warning: 3 spot widths are far outside\n"
    line = _warning_line(RuntimeWarning("using the CPU"), RuntimeWarning, "/a/b.py", 7, "src")
    assert line == "latentz: warning: RuntimeWarning: using the CPU\n"

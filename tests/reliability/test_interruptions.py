"""Interruptions: `latentz localize`, `track` and `simulate` killed with SIGKILL at several
moments leave the previous complete output intact (or, if they finished, the new complete one),
never a truncated file.

A complete output is written first; a second run with different options writes to the same
path and is killed at a fixed delay or as soon as its temporary ``.part`` file appears (the
moment most likely to expose a non-atomic write).
"""

import json
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

from latentz.calibration import Calibration
from latentz.cli import main
from latentz.io import read_table

MOMENTS = (0.3, 1.5, "*.part")


def cli(*args):
    return [sys.executable, "-m", "latentz.cli", *(str(a) for a in args)]


def run_and_kill(args, folder, moment):
    """Run ``args``; SIGKILL it after ``moment`` s or once a file matching it is in ``folder``."""
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    start = time.monotonic()
    while proc.poll() is None and time.monotonic() - start < 60:
        if isinstance(moment, str):
            if any(folder.rglob(moment)):
                break
        elif time.monotonic() - start >= moment:
            break
        time.sleep(0.002)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait() in (0, -signal.SIGKILL), f"{args} failed with status {proc.returncode}"


def assert_table_old_or_new(path, old_bytes, new_table):
    """``path`` holds the old bytes, or a readable table equal to the new run's."""
    assert path.exists(), "the previous complete output was removed"
    if path.read_bytes() != old_bytes:
        table, _ = read_table(path)
        pd.testing.assert_frame_equal(table, new_table)


@pytest.fixture(scope="module")
def inputs(small_microscope, tmp_path_factory):
    folder = tmp_path_factory.mktemp("interrupt")
    src = small_microscope.folder
    cal = folder / "cal.h5"
    result = CliRunner().invoke(
        main,
        ["calibrate", str(src / "stack.tif"), "--z-file", str(src / "z.txt")]
        + ["--field-model", "nearest", "--quiet", "--out", str(cal)],
    )
    assert result.exit_code == 0, result.output
    movie = folder / "long.tif"
    tifffile.imwrite(movie, np.concatenate([small_microscope.gear.frames] * 4))
    return movie, cal


def old_and_new(folder, name, base, change):
    """Bytes of a complete output of ``base`` and the table a run with ``change`` writes."""
    subprocess.run(cli(*base, "--out", folder / name), check=True)
    subprocess.run(cli(*base, *change, "--out", folder / f"new-{name}"), check=True)
    return (folder / name).read_bytes(), read_table(folder / f"new-{name}")[0]


def check_interrupted(tmp_path, name, base, change, reference, moment):
    old, new = reference
    out = tmp_path / name
    out.write_bytes(old)
    run_and_kill(cli(*base, *change, "--out", out), tmp_path, moment)
    assert_table_old_or_new(out, old, new)


LOCALIZE_CHANGE = ("--roi-size", 13)


@pytest.fixture(scope="module")
def localize_args(inputs, tmp_path_factory):
    movie, cal = inputs
    base = ["localize", movie, "--calibration", cal, "--quiet", "--chunk-frames", 5]
    folder = tmp_path_factory.mktemp("localize")
    return base, old_and_new(folder, "locs.parquet", base, LOCALIZE_CHANGE)


@pytest.mark.parametrize("moment", (*MOMENTS, ".locs.parquet.*.part"))
def test_killed_localize_keeps_the_previous_table(localize_args, tmp_path, moment):
    base, reference = localize_args
    check_interrupted(tmp_path, "locs.parquet", base, LOCALIZE_CHANGE, reference, moment)
    # finished chunks of the killed run are complete files (they are what --resume reuses)
    for chunk in (tmp_path / "locs.parquet.chunks").glob("chunk-*.parquet"):
        pd.read_parquet(chunk)


TRACK_CHANGE = ("--seed", 1)


@pytest.fixture(scope="module")
def track_args(localize_args, tmp_path_factory):
    _, (locs, _) = localize_args
    folder = tmp_path_factory.mktemp("track")
    (folder / "locs.parquet").write_bytes(locs)
    base = ["track", folder / "locs.parquet", "--quiet", "--n-sim", 200]
    return base, old_and_new(folder, "motion.csv", base, TRACK_CHANGE)


@pytest.mark.parametrize("moment", MOMENTS)
def test_killed_track_keeps_the_previous_table(track_args, tmp_path, moment):
    base, reference = track_args
    check_interrupted(tmp_path, "motion.csv", base, TRACK_CHANGE, reference, moment)


@pytest.mark.parametrize("moment", (1.5, "*.part"))
def test_killed_calibrate_keeps_the_previous_calibration(
    inputs, small_microscope, tmp_path, moment
):
    _, cal = inputs
    src = small_microscope.folder
    out = tmp_path / "cal.h5"
    out.write_bytes(cal.read_bytes())
    old = Calibration.load(out)
    args = ["calibrate", src / "stack.tif", "--z-file", src / "z.txt", "--field-model", "nearest"]
    run_and_kill(cli(*args, "--shape", "rho", "--quiet", "--out", out), tmp_path, moment)
    again = Calibration.load(out)  # old or new, it is complete
    pd.testing.assert_index_equal(again.scores.columns, old.scores.columns)


def readable(path):
    if path.suffix == ".tif":
        return tifffile.imread(path).shape
    if path.suffix == ".csv":
        return pd.read_csv(path).shape
    return sorted(json.loads(path.read_text()))


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim") / "out"
    subprocess.run(cli("simulate", "gear", "--quick", "--seed", 0, "--out", folder), check=True)
    return {p.name: p.read_bytes() for p in folder.iterdir()}


@pytest.mark.parametrize("moment", (1.5, "*.part"))
def test_killed_simulate_keeps_complete_files(simulated, tmp_path, moment):
    folder = tmp_path / "out"
    folder.mkdir()
    for name, data in simulated.items():
        (folder / name).write_bytes(data)
    shapes = {name: readable(folder / name) for name in simulated}
    run_and_kill(cli("simulate", "gear", "--quick", "--seed", 1, "--out", folder), folder, moment)
    visible = {p.name for p in folder.iterdir() if not p.name.endswith(".part")}
    assert visible == set(simulated)
    for name in simulated:
        # each file is the old one or a complete new one of the same kind and size
        assert readable(folder / name) == shapes[name]


@pytest.mark.xfail(
    strict=True,
    reason="known gap: latentz._shared.atomic.atomic_path removes its temporary file on an "
    "exception, but a SIGKILL during the write leaves the hidden '.<name>.<random>.part' beside "
    "the output (the output itself stays intact)",
)
def test_kill_during_a_write_leaves_no_part_file(track_args, tmp_path):
    base, (old, _) = track_args
    (tmp_path / "motion.csv").write_bytes(old)
    run_and_kill(cli(*base, *TRACK_CHANGE, "--out", tmp_path / "motion.csv"), tmp_path, "*.part")
    assert not [p.name for p in tmp_path.rglob("*.part")]

"""Interruptions: `latentz localize`, `track`, `calibrate` and `simulate` killed with SIGKILL
leave the previous complete output intact, never a truncated or a new half-written file, and
the next run removes the killed run's temporary file.

A complete output is written first; a second run with different options writes to the same
path and is killed either while it starts (0.3 s) or inside the writer: with
``LATENTZ_TEST_PAUSE_WRITING`` naming the output, the atomic writer stops once the new data are
in its temporary ``.part`` file, before the rename, and says so on stderr; the test kills it
there. A writer that wrote in place, or not through the atomic writer, fails: the output would
hold the new bytes, or the pause would never come.
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

from latentz._shared.atomic import PAUSE_ENV
from latentz.calibration import Calibration
from latentz.cli import main
from latentz.io import read_table

#: kill while Python starts (before any output is opened), or inside the write of the output
MOMENTS = (0.3, "write")


def cli(*args):
    return [sys.executable, "-m", "latentz.cli", *(str(a) for a in args)]


def kill_after(args, seconds):
    """Run ``args`` and SIGKILL it after ``seconds``; it must still be running then."""
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(seconds)
    assert proc.poll() is None, f"{args} ended (status {proc.returncode}) before the kill"
    proc.kill()
    assert proc.wait() == -signal.SIGKILL


def kill_in_write(args, name):
    """Run ``args`` with the writer of output ``name`` paused once its data are in the
    temporary file; SIGKILL it there. Returns that temporary file's name."""
    env = {**os.environ, PAUSE_ENV: name}
    proc = subprocess.Popen(
        args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env
    )
    line = ""
    for line in proc.stderr:
        if line.startswith("latentz: paused writing"):
            proc.kill()
            break
    proc.stderr.close()
    status = proc.wait()
    assert status == -signal.SIGKILL, f"{args} never paused inside the write of {name}"
    return line.rsplit(" in ", 1)[1].strip()


def interrupt(args, folder, name, moment):
    """Kill ``args`` at ``moment``; the temporary files of ``name`` it left in ``folder``."""
    if moment == "write":
        part = kill_in_write(args, name)
        assert (folder / part).exists(), "the kill landed outside the write"
    else:
        kill_after(args, moment)
    return sorted(folder.glob(f".{name}.*.part"))


def old_and_new(folder, name, base, change):
    """Bytes of a complete output of ``base`` and the table a run with ``change`` writes."""
    subprocess.run(cli(*base, "--out", folder / name), check=True)
    subprocess.run(cli(*base, *change, "--out", folder / f"new-{name}"), check=True)
    old = (folder / name).read_bytes()
    assert old != (folder / f"new-{name}").read_bytes(), "the change must change the output"
    return old, read_table(folder / f"new-{name}")[0]


def check_interrupted(tmp_path, name, base, change, reference, moment):
    """Killed, the run leaves the old bytes; run again, it writes the new table and removes the
    killed run's temporary file."""
    old, new = reference
    out = tmp_path / name
    out.write_bytes(old)
    left = interrupt(cli(*base, *change, "--out", out), tmp_path, name, moment)
    assert out.read_bytes() == old, "the previous complete output changed"
    assert len(left) == (moment == "write")
    subprocess.run(cli(*base, *change, "--out", out), check=True)
    pd.testing.assert_frame_equal(read_table(out)[0], new)
    assert not list(tmp_path.glob(f".{name}.*.part")), "the killed run's .part file is left"


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


LOCALIZE_CHANGE = ("--roi-size", 13)


@pytest.fixture(scope="module")
def localize_args(inputs, tmp_path_factory):
    movie, cal = inputs
    base = ["localize", movie, "--calibration", cal, "--quiet", "--chunk-frames", 5]
    folder = tmp_path_factory.mktemp("localize")
    return base, old_and_new(folder, "locs.parquet", base, LOCALIZE_CHANGE)


@pytest.mark.parametrize("moment", MOMENTS)
def test_killed_localize_keeps_the_previous_table(localize_args, tmp_path, moment):
    base, reference = localize_args
    check_interrupted(tmp_path, "locs.parquet", base, LOCALIZE_CHANGE, reference, moment)


def test_localize_killed_inside_a_chunk_keeps_the_finished_chunks(localize_args, tmp_path):
    """Killed while writing its third chunk (frames 10-14), the run leaves the old table and
    two complete chunks (what --resume reuses), and no chunk of the killed write."""
    base, (old, _) = localize_args
    out = tmp_path / "locs.parquet"
    out.write_bytes(old)
    chunks = tmp_path / "locs.parquet.chunks"
    third = "chunk-000000010-000000015.parquet"
    interrupt(cli(*base, *LOCALIZE_CHANGE, "--out", out), chunks, third, "write")
    assert out.read_bytes() == old
    finished = sorted(p.name for p in chunks.glob("chunk-*.parquet"))
    assert finished == ["chunk-000000000-000000005.parquet", "chunk-000000005-000000010.parquet"]
    for name in finished:
        assert len(pd.read_parquet(chunks / name)) > 0


TRACK_CHANGE = ("--search-range-nm", 500)  # links fewer steps: another motion table


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


@pytest.mark.parametrize("moment", MOMENTS)
def test_killed_calibrate_keeps_the_previous_calibration(
    inputs, small_microscope, tmp_path, moment
):
    _, cal = inputs
    src = small_microscope.folder
    out = tmp_path / "cal.h5"
    old = cal.read_bytes()
    out.write_bytes(old)
    args = ["calibrate", src / "stack.tif", "--z-file", src / "z.txt", "--field-model", "nearest"]
    args = cli(*args, "--shape", "rho", "--quiet", "--out", out)
    left = interrupt(args, tmp_path, "cal.h5", moment)
    assert out.read_bytes() == old, "the previous calibration changed"
    assert len(left) == (moment == "write")
    subprocess.run(args, check=True)
    assert Calibration.load(out).shape == "rho"  # the new one, complete
    assert not list(tmp_path.glob(".cal.h5.*.part")), "the killed run's .part file is left"


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


@pytest.mark.parametrize("moment", (0.3, "gear_truth.csv", "gear_movie.tif"))
def test_killed_simulate_keeps_complete_files(simulated, tmp_path, moment):
    """Each file is the old one or a complete new one of the same kind and size; the one
    being written when the kill came is the old one."""
    folder = tmp_path / "out"
    folder.mkdir()
    for name, data in simulated.items():
        (folder / name).write_bytes(data)
    shapes = {name: readable(folder / name) for name in simulated}
    args = cli("simulate", "gear", "--quick", "--seed", 1, "--out", folder)
    if isinstance(moment, str):
        interrupt(args, folder, moment, "write")
        assert (folder / moment).read_bytes() == simulated[moment]
    else:
        interrupt(args, folder, "gear_movie.tif", moment)
    visible = {p.name for p in folder.iterdir() if not p.name.endswith(".part")}
    assert visible == set(simulated)
    for name in simulated:
        assert readable(folder / name) == shapes[name]
    subprocess.run(args, check=True)
    assert not list(folder.glob(".*.part")), "the killed run's .part file is left"

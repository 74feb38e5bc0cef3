import os
import signal
import subprocess
import sys

import dask.array as da
import numpy as np
import pandas as pd
import pytest
import tifffile

from latentz.io import as_frames, read_stack, read_table, write_table


def test_read_stack_is_lazy_and_exact(tmp_path):
    rng = np.random.default_rng(1)
    stack = rng.integers(0, 65535, size=(7, 20, 30), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "s.tif", stack)
    lazy = read_stack(tmp_path / "s.tif")
    assert isinstance(lazy, da.Array)
    assert lazy.shape == (7, 20, 30)
    np.testing.assert_array_equal(lazy.compute(), stack)


def test_read_stack_ome_tiff(tmp_path):
    stack = np.arange(3 * 8 * 9, dtype=np.uint16).reshape(3, 8, 9)
    tifffile.imwrite(tmp_path / "s.ome.tif", stack, ome=True, metadata={"axes": "ZYX"})
    np.testing.assert_array_equal(read_stack(tmp_path / "s.ome.tif").compute(), stack)


def test_single_image_becomes_one_frame(tmp_path):
    tifffile.imwrite(tmp_path / "one.tif", np.ones((5, 6), np.uint16))
    assert read_stack(tmp_path / "one.tif").shape == (1, 5, 6)


def test_read_stack_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="No such image"):
        read_stack(tmp_path / "missing.tif")
    (tmp_path / "bad.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(ValueError, match="Cannot read"):
        read_stack(tmp_path / "bad.tif")
    tifffile.imwrite(
        tmp_path / "4d.tif", np.zeros((2, 3, 4, 5), np.uint16), photometric="minisblack"
    )
    with pytest.raises(ValueError, match="frames, rows, columns"):
        read_stack(tmp_path / "4d.tif")
    (tmp_path / "x.png").write_bytes(b"")
    with pytest.raises(ValueError, match=".tif"):
        read_stack(tmp_path / "x.png")


def test_truncated_tiff_is_a_clear_error(tmp_path):
    stack = np.ones((10, 32, 32), np.uint16)
    tifffile.imwrite(tmp_path / "t.tif", stack)
    data = (tmp_path / "t.tif").read_bytes()
    (tmp_path / "t.tif").write_bytes(data[: len(data) // 3])
    with pytest.raises(ValueError, match="t.tif"):
        read_stack(tmp_path / "t.tif").compute()


def test_as_frames_accepts_numpy_dask_and_paths(tmp_path):
    image = np.ones((4, 5))
    assert as_frames(image).shape == (1, 4, 5)
    assert isinstance(as_frames(da.ones((2, 4, 5))), da.Array)
    with pytest.raises(ValueError, match="2 or 3 dimensions"):
        as_frames(np.ones((2, 2, 2, 2)))
    with pytest.raises(ValueError, match="non-empty"):
        as_frames(np.ones((0, 4, 5)))
    with pytest.raises(TypeError, match="dtype"):
        as_frames(np.array([["a"]]))


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_table_round_trip_with_metadata(tmp_path, suffix):
    table = pd.DataFrame({"frame": [0, 1, 2], "x": [1.5, 2.5, 3.25], "z_nm": [-10.0, 0.0, 10.0]})
    path = write_table(table, tmp_path / f"locs{suffix}", metadata={"calibration": "cal.h5"})
    back, meta = read_table(path)
    pd.testing.assert_frame_equal(back, table)
    assert meta == {"calibration": "cal.h5"}
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


def test_write_table_refuses_unknown_format(tmp_path):
    with pytest.raises(ValueError, match="format"):
        write_table(pd.DataFrame({"a": [1]}), tmp_path / "t.xlsx")


def test_failed_write_keeps_the_previous_file(tmp_path):
    path = tmp_path / "t.csv"
    write_table(pd.DataFrame({"a": [1, 2]}), path)
    before = path.read_bytes()

    class Boom(pd.DataFrame):
        def to_csv(self, *args, **kwargs):
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        write_table(Boom({"a": [3]}), path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


def test_kill_during_write_leaves_no_partial_file(tmp_path):
    """A writer killed with SIGKILL mid-write leaves either nothing or the complete old file."""
    target = tmp_path / "big.parquet"
    code = (
        "import numpy as np, pandas as pd, sys\n"
        "from latentz.io import write_table\n"
        "t = pd.DataFrame(np.random.default_rng(0).normal(size=(3_000_000, 8)))\n"
        "t.columns = [str(c) for c in t.columns]\n"
        "print('ready', flush=True)\n"
        f"write_table(t, {str(target)!r})\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"ready"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    if target.exists():  # the rename happened before the kill: the file must be complete
        back, _ = read_table(target)
        assert back.shape == (3_000_000, 8)

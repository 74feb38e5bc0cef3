import os
import signal
import subprocess
import sys
import textwrap

import pandas as pd
import pytest

from latentz.cli.chunked import chunk_dir, run_chunked
from latentz.io import read_table


def _process(calls):
    def process(start, stop):
        calls.append((start, stop))
        return pd.DataFrame(
            {"frame": range(start, stop), "v": [f * 2.0 for f in range(start, stop)]}
        )

    return process


def test_chunks_concatenate_in_order_and_work_folder_is_removed(tmp_path):
    calls = []
    out = tmp_path / "locs.parquet"
    result = run_chunked(
        25, _process(calls), out, manifest={"a": 1}, chunk_frames=10, metadata={"calibration": "x"}
    )
    assert calls == [(0, 10), (10, 20), (20, 25)]
    back, meta = read_table(out)
    assert back["frame"].tolist() == list(range(25))
    pd.testing.assert_frame_equal(back, result)
    assert meta == {"calibration": "x"}
    assert not chunk_dir(out).exists()


def test_resume_reuses_finished_chunks_only_when_manifest_matches(tmp_path):
    out = tmp_path / "locs.parquet"
    calls = []

    def failing(start, stop):
        if start == 20:
            raise KeyboardInterrupt
        return _process(calls)(start, stop)

    with pytest.raises(KeyboardInterrupt):
        run_chunked(30, failing, out, manifest={"a": 1}, chunk_frames=10)
    assert not out.exists() and calls == [(0, 10), (10, 20)]
    calls.clear()
    run_chunked(30, _process(calls), out, manifest={"a": 1}, chunk_frames=10, resume=True)
    assert calls == [(20, 30)]
    assert read_table(out)[0]["frame"].tolist() == list(range(30))


def test_resume_with_other_options_is_refused(tmp_path):
    out = tmp_path / "locs.parquet"
    with pytest.raises(KeyboardInterrupt):
        run_chunked(
            20,
            lambda s, e: (_ for _ in ()).throw(KeyboardInterrupt),
            out,
            manifest={"a": 1},
            chunk_frames=10,
        )
    with pytest.raises(ValueError, match="Cannot resume"):
        run_chunked(20, _process([]), out, manifest={"a": 2}, chunk_frames=10, resume=True)


def test_kill_9_leaves_no_output_and_resume_finishes(tmp_path):
    out = tmp_path / "locs.parquet"
    script = textwrap.dedent(
        f"""
        import sys, time, pandas as pd
        from latentz.cli.chunked import run_chunked
        def process(start, stop):
            if start >= 30 and sys.argv[1] == "slow":
                print("chunk", start, flush=True); time.sleep(60)
            return pd.DataFrame({{"frame": range(start, stop)}})
        run_chunked(50, process, {str(out)!r}, manifest={{"m": 1}}, chunk_frames=10,
                    resume=True)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script, "slow"], stdout=subprocess.PIPE)
    assert proc.stdout.readline().startswith(b"chunk 30")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists()
    assert len(list(chunk_dir(out).glob("chunk-*.parquet"))) == 3
    subprocess.run([sys.executable, "-c", script, "fast"], check=True)
    assert read_table(out)[0]["frame"].tolist() == list(range(50))

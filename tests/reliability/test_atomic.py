"""The atomic writer removes temporary files that killed writers left beside the same output,
and only those: a live writer's file stays."""

import os
import subprocess
import sys

from latentz._shared.atomic import write_text_atomic


def test_the_next_write_removes_a_killed_writers_part_file(tmp_path):
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()  # its pid now names no process
    orphan = tmp_path / f".out.csv.{ended.pid}.abc123.part"
    live = tmp_path / f".out.csv.{os.getpid()}.def456.part"  # a write under way in this process
    other = tmp_path / f".other.csv.{ended.pid}.ghi789.part"  # another output's
    for path in (orphan, live, other):
        path.write_text("half")
    write_text_atomic(tmp_path / "out.csv", "a,b\n")
    assert (tmp_path / "out.csv").read_text() == "a,b\n"
    assert not orphan.exists() and live.exists() and other.exists()

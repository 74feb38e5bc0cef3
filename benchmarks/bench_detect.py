"""Detection speed-up of issue 14: `detect_arrays` against the SciPy version it replaced.

The old `latentz.detect` (commit 4f355ea, read with git) and the new one detect the same four
2048 x 2048 frames of 30 spots (`bench_localize.spots_movie`), in turns, three rounds.

    python benchmarks/bench_detect.py      # prints frames/s of both and the ratio per round
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OLD = "4f355ea:src/latentz/detect.py"


def old_detect():
    source = subprocess.run(["git", "show", OLD], capture_output=True, text=True, check=True)
    name = "old_detect"
    path = Path(tempfile.mkdtemp()) / f"{name}.py"
    path.write_text(source.stdout)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_localize import spots_movie

    from latentz.detect.api import detect_arrays

    old = old_detect()
    frames = spots_movie(4, 30).astype(np.float64)
    detect_arrays(frames[:1])
    times = {"old": [], "new": []}
    counts = {}
    for _ in range(3):
        for name, run in (("old", old.detect_arrays), ("new", detect_arrays)):
            start = time.perf_counter()
            counts[name] = len(run(frames).frame)
            times[name].append(time.perf_counter() - start)
    ratio = np.array(times["old"]) / np.array(times["new"])
    for name in times:
        print(f"{name}: {4 / min(times[name]):.2f} frames/s, {counts[name]} detections of 120")
    print(f"speed-up per round: {np.round(ratio, 1)}")


if __name__ == "__main__":
    main()

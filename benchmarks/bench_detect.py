"""Detection speed-up of issue 14: `detect_arrays` against the SciPy version it replaced.

The old `latentz.detect` (commit 4f355ea, read with git) and the new one detect the same four
2048 x 2048 frames of 30 spots (benchmarks/bench_localize.spots_movie), in turns, three rounds.

    python benchmarks/bench_detect.py      # prints frames/s of both and the ratio per round
"""

import importlib.util
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_localize import spots_movie  # noqa: E402

src = subprocess.run(
    ["git", "show", "4f355ea:src/latentz/detect.py"], capture_output=True, text=True
).stdout
open("/tmp/speed_old_detect.py", "w").write(src)
spec = importlib.util.spec_from_file_location("old_detect", "/tmp/speed_old_detect.py")
old = importlib.util.module_from_spec(spec)
spec.loader.exec_module(old)
from latentz.detect import detect_arrays  # noqa: E402

frames = spots_movie(4, 30).astype(np.float64)
detect_arrays(frames[:1])
t_old, t_new = [], []
for _ in range(3):
    t = time.perf_counter()
    a = old.detect_arrays(frames)
    t_old.append(time.perf_counter() - t)
    t = time.perf_counter()
    b = detect_arrays(frames)
    t_new.append(time.perf_counter() - t)
r = np.array(t_old) / np.array(t_new)
print(
    f"old {4 / min(t_old):.2f} fps ({len(a.frame)} det), new {4 / min(t_new):.2f} fps ({len(b.frame)} det), ratio per round {np.round(r, 1)}"
)

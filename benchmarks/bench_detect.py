"""Detection speed of `detect_arrays` against an earlier revision of `latentz.detect`.

The earlier `latentz.detect` package (read with git, default: the three-pass kernels before the
fused pass of issue 30) and the current one detect the same 2048 x 2048 uint16 frames with 30
spots (`bench_localize.spots_movie` through a camera of offset 100 ADU, gain 0.5), in turns,
several rounds: on a loaded machine only the ratio of times measured back to back, and the CPU
time of the process, mean much.
The detections of both are compared too: frame, row, col, ROI corners and flags.

    python benchmarks/bench_detect.py [--old d0e1c10] [--frames 8] [--rounds 5] [--seed 1]
"""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PACKAGE = "src/latentz/detect"


def old_detect(revision: str):
    """The `latentz.detect` package at ``revision``, imported as ``old_detect``."""
    folder = Path(tempfile.mkdtemp()) / "old_detect"
    folder.mkdir()
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{revision}:{PACKAGE}"],
                           capture_output=True, text=True, check=True).stdout.split()  # fmt: skip
    for name in names:
        source = subprocess.run(["git", "show", f"{revision}:{PACKAGE}/{name}"],
                                capture_output=True, text=True, check=True).stdout  # fmt: skip
        (folder / name).write_text(source.replace("latentz.detect", "old_detect"))
    sys.path.insert(0, str(folder.parent))
    return importlib.import_module("old_detect.api")


def cpu_seconds() -> float:
    """CPU time of this process, all threads (user + system), s: on a loaded machine it counts
    the work, not the waits for a core."""
    used = os.times()
    return used.user + used.system


def same(a, b) -> bool:
    """Whether two `Detections` hold the same emitters (scores to float32 rounding)."""
    keys = ("frame", "row", "col", "row0", "col0", "edge", "close_pair")
    equal = all(np.array_equal(getattr(a, k), getattr(b, k)) for k in keys)
    return equal and np.allclose(a.snr, b.snr, rtol=1e-4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", default="d0e1c10")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--spots", type=int, default=30)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_localize import spots_movie

    from latentz.camera import Camera
    from latentz.detect.api import detect_arrays

    old = old_detect(args.old)
    camera = Camera(offset=100.0, gain=0.5)
    photons = spots_movie(args.frames, args.spots, seed=args.seed)
    frames = np.round(photons / camera.gain + camera.offset).astype(np.uint16)
    runs = {"old": old.detect_arrays, "new": detect_arrays}
    found = {name: run(frames, roi_size=15, camera=camera) for name, run in runs.items()}
    times = {name: [] for name in runs}
    cpu = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, run in runs.items():
            start, used = time.perf_counter(), cpu_seconds()
            run(frames, roi_size=15, camera=camera)
            times[name].append(time.perf_counter() - start)
            cpu[name].append(cpu_seconds() - used)
    ratio = np.array(times["old"]) / np.array(times["new"])
    for name in runs:
        rates = args.frames / np.array(times[name])
        per_frame = 1e3 * np.array(cpu[name]) / args.frames
        print(f"{name}: {rates.max():.1f} frames/s best, {np.median(rates):.1f} median; CPU "
              f"{per_frame.min():.1f} ms per frame best, {np.median(per_frame):.1f} median; "
              f"{len(found[name].frame)} detections")  # fmt: skip
    print(f"old / new time per round: {np.round(ratio, 2)}; median {np.median(ratio):.2f}, "
          f"best-to-best {min(times['old']) / min(times['new']):.2f}")  # fmt: skip
    print(f"same detections: {same(found['old'], found['new'])}")


if __name__ == "__main__":
    main()

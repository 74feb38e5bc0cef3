"""Throughput and peak memory of `latentz localize` on a long movie (issue 7, item 3).

Writes a simulated 512 x 512 movie with about 30 emitters per frame to a TIFF on disk, calibrates
on a small simulated calibration of the same microscope, then runs the CLI (`latentz localize`,
chunked and resumable, with the calibration applied) in a child process for movies of several
lengths, and reports frames/s against the paper's acquisition rate (90.9 Hz) and the child's peak
resident memory. Memory must stay flat with movie length: frames are read lazily chunk by chunk.

    python benchmarks/bench_localize.py [--frames 500 2000] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

FIELD = (512, 512)
PAPER_HZ = 90.9


def make_inputs(folder: Path, n_frames_max: int, seed: int = 0) -> tuple[Path, dict[int, Path]]:
    from latentz import simulate as sim
    from latentz.calibration import calibrate

    aberrations = sim.AberrationMap.default(seed=seed, field_shape=FIELD)
    data = sim.calibration_dataset(
        n_particles=60,
        z_nm=np.linspace(-2000, 2000, 41),
        n_stage_positions=1,
        frame_shape=FIELD,
        min_spacing_px=40.0,
        aberrations=aberrations,
        seed=seed,
    )
    cal = calibrate(list(data.stacks), data.z_nm, field_model="nearest", camera=data.camera)
    cal_path = folder / "cal.h5"
    cal.save(cal_path)
    rng = np.random.default_rng(seed)
    n_distinct, per_frame = 40, 30
    spots = pd.DataFrame(
        {
            "frame": np.repeat(np.arange(n_distinct), per_frame),
            "x": rng.uniform(12, FIELD[1] - 12, n_distinct * per_frame),
            "y": rng.uniform(12, FIELD[0] - 12, n_distinct * per_frame),
            "z_nm": rng.uniform(-1500, 1500, n_distinct * per_frame),
        }
    )
    frames, _ = sim.render_spots(
        spots, frame_shape=FIELD, aberrations=aberrations, photons=5e5, background=100.0, seed=seed
    )
    movies = {}
    for n in sorted(set(n_frames_max)):
        path = folder / f"movie_{n}.tif"
        with tifffile.TiffWriter(path, bigtiff=True) as tif:
            for i in range(n):
                tif.write(frames[i % n_distinct], contiguous=True)
        movies[n] = path
    return cal_path, movies


def run_child(movie: Path, cal: Path, out: Path) -> tuple[float, float]:
    """Wall time (s) and peak RSS (MiB) of one `latentz localize` child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "latentz.cli",
            "localize",
            str(movie),
            "--calibration",
            str(cal),
            "--quiet",
            "--out",
            str(out),
        ],
        check=True,
    )
    elapsed = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if peak < before:  # ru_maxrss is the max over all children so far
        peak = before
    return elapsed, peak / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[500, 2000])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cal, movies = make_inputs(folder, args.frames)
        # warm the numba cache so the first timed run is not charged with compilation
        run_child(movies[min(movies)], cal, folder / "warm.parquet")
        for n, movie in sorted(movies.items()):
            seconds, peak_mib = run_child(movie, cal, folder / f"locs_{n}.parquet")
            locs = pd.read_parquet(folder / f"locs_{n}.parquet")
            rows.append(
                {
                    "frames": n,
                    "frame_size": f"{FIELD[0]}x{FIELD[1]}",
                    "localizations": len(locs),
                    "seconds": round(seconds, 1),
                    "frames_per_s": round(n / seconds, 1),
                    "vs_paper_90.9_Hz": round(n / seconds / PAPER_HZ, 2),
                    "peak_rss_mib (max over runs so far)": round(peak_mib),
                }
            )
    table = pd.DataFrame(rows)
    text = table.to_markdown(index=False)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_localize.md").write_text(
        "# `latentz localize` throughput and memory (benchmarks/bench_localize.py)\n\n"
        f"{os.cpu_count()} cores; child process per run; calibration applied.\n\n{text}\n"
    )


if __name__ == "__main__":
    main()

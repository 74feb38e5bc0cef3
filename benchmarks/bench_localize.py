"""Localization speed at the acquisition rate (issue 14) and CLI memory (issue 7).

Default: `lz.localize` throughput on 2048 x 2048 frames against the paper's rate, 90.9 Hz
(1 / (1 ms + 1024 row pairs x 10 us)), written to ``results/bench_localize_rate.md``:

- full detection with 30 and 500 Gaussian spots per frame (sd 1.3-3 px, 5000 photons, background
  50 photons/px), from memory (float32 photoelectrons) and from an uncompressed TIFF;
- full and tracking mode on 28 spots turning on a ring (1.8 px per frame, 0.3 px play; the
  demo's gear moves ~120 px per frame with ~30 px of play, one frame per cycle, which no
  prediction follows), from memory and from TIFF, with the fraction of true positions found
  within 0.5 px and the number of rows fitted from predictions;
- full detection of a TIFF path on a process-based dask.distributed ``LocalCluster`` of 1 and 2
  workers (one thread each).

Frames/s are the best of ``--rounds`` runs after a warm-up (the numba kernels compiled).

    python benchmarks/bench_localize.py [--frames 60] [--rounds 3] [--out benchmarks/results]
                                        [--cases spots moving]
    python benchmarks/bench_localize.py --cli [--frames 500 2000]    # issue 7: CLI memory

With ``--cli``: writes a simulated 512 x 512 movie with about 30 emitters per frame to a TIFF on
disk, calibrates on a small simulated calibration of the same microscope, then runs the CLI
(`latentz localize`, chunked and resumable, with the calibration applied) in a child process for
movies of several lengths, and reports frames/s against the paper's acquisition rate (90.9 Hz)
and the child's peak resident memory (``results/bench_localize.md``). Memory must stay flat with
movie length: frames are read lazily chunk by chunk.
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
from typing import Any

import numpy as np
import pandas as pd
import tifffile

FIELD = (512, 512)
PAPER_HZ = 90.9
#: Row groups of the rate table: spots per frame (full detection, local and on a dask
#: cluster) and the moving spots (full and tracking mode).
CASES = ("spots", "moving")


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


def spots_movie(n_frames: int, per_frame: int, seed: int = 0) -> np.ndarray:
    """Poisson frames (n, 2048, 2048) float32 photoelectrons with ``per_frame`` round spots."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(20, 2028, (n_frames, per_frame, 2))
    return render_frames(xy, rng.uniform(1.3, 3.0, (n_frames, per_frame)), rng)


def moving_movie(n_frames: int, seed: int = 0) -> tuple[np.ndarray, pd.DataFrame]:
    """28 spots (sd 1.5 px) on a ring of radius 900 px turning 2 mrad (1.8 px) per frame, with
    0.3 px of random play: Poisson frames (n, 2048, 2048) and the truth (frame, x, y)."""
    rng = np.random.default_rng(seed)
    angle = 2 * np.pi * np.arange(28) / 28 + 0.002 * np.arange(n_frames)[:, None]
    xy = 1023.5 + 900.0 * np.stack([np.cos(angle), np.sin(angle)], axis=2)
    xy += rng.normal(0.0, 0.3, xy.shape)
    truth = pd.DataFrame({"frame": np.repeat(np.arange(n_frames), 28),
                          "x": xy[..., 0].ravel(), "y": xy[..., 1].ravel()})  # fmt: skip
    return render_frames(xy, np.full(xy.shape[:2], 1.5), rng), truth


def render_frames(xy: np.ndarray, widths: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson frames (n, 2048, 2048) float32: round spots of 5000 photons at ``xy`` (n, k, 2)
    px with sd ``widths`` (n, k) px on 50 photons/px."""
    from latentz.fit import amplitude_of, render_rois

    size, half = 2048, 12
    n_frames, per_frame = xy.shape[:2]
    frames = np.empty((n_frames, size, size), np.float32)
    for t in range(n_frames):
        x, y = xy[t, :, 0], xy[t, :, 1]
        wd = widths[t]
        col, row = x.astype(int), y.astype(int)
        table = pd.DataFrame({"x": x - col + half, "y": y - row + half, "background": 0.0,
                              "wx": wd, "wy": wd, "rho": 0.0})  # fmt: skip
        table["amplitude"] = amplitude_of(5000.0, wd, wd, 0.0)
        patches = render_rois(table, shape=2 * half + 1)
        expected = np.full((size, size), 50.0)
        for k in range(per_frame):
            expected[row[k] - half : row[k] + half + 1, col[k] - half : col[k] + half + 1] += (
                patches[k]
            )
        frames[t] = rng.poisson(expected)
    return frames


def best_rate(run, n_frames: int, rounds: int) -> tuple[float, Any]:
    """(best frames/s over ``rounds`` runs, the last result)."""
    best, result = np.inf, None
    for _ in range(rounds):
        start = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - start)
    return n_frames / best, result


def within(locs: pd.DataFrame, truth: pd.DataFrame, radius: float = 0.5) -> float:
    """Fraction of true positions with a converged localization within ``radius`` px."""
    from scipy.spatial import cKDTree

    hits = 0
    for frame, group in truth.groupby("frame"):
        found = locs[(locs.frame == frame) & locs.converged]
        if len(found):
            dist, _ = cKDTree(found[["x", "y"]].to_numpy()).query(group[["x", "y"]].to_numpy())
            hits += int((dist < radius).sum())
    return hits / len(truth)


def rate_main(args: argparse.Namespace) -> None:
    from latentz.localization import localize

    rows = []

    def add(case: str, source: str, rate: float, locs: pd.DataFrame, n: int, **extra) -> None:
        rows.append({"case": case, "input": source, "frames": n, "localizations": len(locs),
                     "frames_per_s": round(rate, 1), "vs_90.9_Hz": round(rate / PAPER_HZ, 2),
                     **extra})  # fmt: skip
        print(rows[-1], flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        for per_frame in (30, 500) if "spots" in args.cases else ():
            frames = spots_movie(args.frames, per_frame)
            path = Path(tmp) / f"spots_{per_frame}.tif"
            tifffile.imwrite(path, frames)
            localize(frames[:2])
            for source, movie in (("memory", frames), ("TIFF", path)):
                rate, locs = best_rate(lambda m=movie: localize(m), args.frames, args.rounds)
                add(f"full, {per_frame} spots/frame", source, rate, locs, args.frames)
            if per_frame == 30:
                for workers in args.workers:
                    rate, locs = cluster_rate(path, workers, args.frames, args.rounds)
                    add(f"full, {per_frame} spots/frame", f"TIFF, {workers} dask workers", rate,
                        locs, args.frames)  # fmt: skip
            del frames
        if "moving" not in args.cases:
            return write_rate_table(rows, args)
        frames, truth = moving_movie(args.frames)
        path = Path(tmp) / "moving.tif"
        tifffile.imwrite(path, frames)
        localize(frames[:3], track=True)
        for mode in ("full", "tracking"):
            for source, movie in (("memory", frames), ("TIFF", path)):
                rate, locs = best_rate(
                    lambda m=movie, k=mode: localize(m, track=k == "tracking"),
                    args.frames,
                    args.rounds,
                )
                add(f"28 moving spots, {mode}", source, rate, locs, args.frames,
                    within_0_5_px=round(within(locs, truth), 4),
                    predicted_rows=int(locs.snr.isna().sum()))  # fmt: skip
    write_rate_table(rows, args)


def write_rate_table(rows: list[dict], args: argparse.Namespace) -> None:
    table = pd.DataFrame(rows).to_markdown(index=False)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_localize_rate.md").write_text(
        "# `lz.localize` on 2048 x 2048 frames against 90.9 Hz (benchmarks/bench_localize.py)\n\n"
        f"{os.cpu_count()} cores, numba threads {numba_threads()}; best of {args.rounds} runs.\n\n"
        f"{table}\n"
    )


def numba_threads() -> int:
    import numba

    return numba.get_num_threads()


def cluster_rate(path: Path, workers: int, n_frames: int, rounds: int) -> tuple[float, Any]:
    """Frames/s of `localize(path)` on a process-based LocalCluster of ``workers`` x 1 thread."""
    from distributed import Client, LocalCluster

    from latentz.localization import localize

    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                     dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):  # fmt: skip
        localize(path, scheduler=client, chunk_frames=2)  # warm the workers
        return best_rate(lambda: localize(path, scheduler=client, chunk_frames=4), n_frames, rounds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cli", action="store_true", help="the issue 7 CLI memory benchmark")
    parser.add_argument("--frames", type=int, nargs="+", default=None)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES),
                        help="which rows of the rate table to measure (default all)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    if args.cli:
        args.frames = args.frames or [500, 2000]
        cli_main(args)
    else:
        args.frames = (args.frames or [60])[0]
        rate_main(args)


def cli_main(args: argparse.Namespace) -> None:
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

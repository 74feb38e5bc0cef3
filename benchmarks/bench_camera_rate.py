"""`lz.localize` on 2048 x 2048 uint16 camera frames against 90.9 Hz, two source trees compared.

Each case runs in a child process per source tree (``PYTHONPATH`` set to it), the trees taking
turns, so that a loaded machine slows both alike; the ratio after / before is what counts there.
Cases, all with a camera (offset 100 ADU, gain 1, read noise 1.5 e-):

- ``30``, ``500``: `lz.localize(frames, camera=cam)` on uint16 frames in memory, 30 or 500 round
  spots per frame (sd 1.3-3 px, 5000 photons, background 50 photons/px);
- ``30-tiff``: the same 30-spot movie from an uncompressed TIFF path;
- ``calibrated``: `lz.localize(frames, calibration=cal)` on 30 spots per frame rendered with the
  calibrated microscope's aberrations and camera (z uniform in +-1.5 um), the calibration made
  on a simulated 2048 x 2048 stack of the same microscope;
- ``tracking``: `lz.localize(frames, camera=cam, track=True)` on 28 spots turning on a ring;
- ``fit_rois``: `lz.fit_rois` on 20 000 ROIs of 11 x 11 px (ROIs per second).

    python benchmarks/bench_camera_rate.py --before /tmp/before/src [--frames 16] [--rounds 3]
        [--turns 1] [--threads N] [--cases 30 30-tiff 500 calibrated tracking fit_rois]

``--before`` is the ``src`` folder of the tree to compare with, for example
``git archive main src | tar -x -C /tmp/before``. Writes one results file per set of cases,
``bench_camera_rate_<cases>.md`` beside the other results: frames/s as the median (min-max) over
the rounds of each tree, and the ratio of the medians. ``--threads 1`` runs the children on one
thread (``NUMBA_NUM_THREADS``): frames per CPU second then hold no threads waiting for each other,
the comparison of two trees that a loaded machine disturbs least.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _rounds import machine, spread, write_results  # noqa: E402

PAPER_HZ = 90.9
CASES = ("30", "30-tiff", "500", "calibrated", "tracking", "fit_rois")
AFTER = Path(__file__).resolve().parents[1] / "src"
SHAPE = (2048, 2048)
OFFSET, GAIN, READNOISE = 100.0, 1.0, 1.5
N_ROIS = 20000


def _camera():
    from latentz.camera import Camera

    return Camera(offset=OFFSET, gain=GAIN, readnoise=READNOISE)


def _adu(photons: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(photons / GAIN + OFFSET), 0, 65535).astype(np.uint16)


def make_inputs(folder: Path, n_frames: int, cases: list[str]) -> None:
    """Write every case's input to ``folder`` (made once, read by every child)."""
    import tifffile
    from bench_localize import moving_movie, spots_movie

    if {"30", "30-tiff"} & set(cases):
        frames = _adu(spots_movie(n_frames, 30))
        np.save(folder / "spots_30.npy", frames)
        tifffile.imwrite(folder / "spots_30.tif", frames)
    if "500" in cases:
        np.save(folder / "spots_500.npy", _adu(spots_movie(n_frames, 500)))
    if "tracking" in cases:
        np.save(folder / "moving.npy", _adu(moving_movie(n_frames)[0]))
    if "calibrated" in cases:
        make_calibrated(folder, n_frames)
    if "fit_rois" in cases:
        make_rois(folder)


def make_calibrated(folder: Path, n_frames: int, seed: int = 3) -> None:
    """A calibration of a simulated 2048 x 2048 microscope and a movie of 30 spots per frame
    of the same microscope (8 distinct frames, repeated)."""
    from latentz import simulate as sim
    from latentz.calibration import calibrate

    aberrations = sim.AberrationMap.default(seed=seed, field_shape=SHAPE)
    data = sim.calibration_dataset(
        n_particles=30, z_nm=np.linspace(-2000, 2000, 21), n_stage_positions=1,
        frame_shape=SHAPE, min_spacing_px=150.0, aberrations=aberrations, seed=seed,
    )  # fmt: skip
    cal = calibrate(list(data.stacks), data.z_nm, field_model="nearest", camera=data.camera)
    cal.save(folder / "cal.h5")
    rng = np.random.default_rng(seed)
    distinct, per_frame = 8, 30
    spots = pd.DataFrame({
        "frame": np.repeat(np.arange(distinct), per_frame),
        "x": rng.uniform(20, SHAPE[1] - 20, distinct * per_frame),
        "y": rng.uniform(20, SHAPE[0] - 20, distinct * per_frame),
        "z_nm": rng.uniform(-1500, 1500, distinct * per_frame),
    })  # fmt: skip
    frames, _ = sim.render_spots(spots, frame_shape=SHAPE, aberrations=aberrations,
                                 photons=2e4, background=50.0, seed=seed)  # fmt: skip
    np.save(folder / "calibrated.npy", frames[np.arange(n_frames) % distinct])  # uint16 ADU


def make_rois(folder: Path, seed: int = 4) -> None:
    """20 000 ROIs of 11 x 11 px: one round spot of 2000 photons each on 20 photons/px."""
    from latentz.fit import amplitude_of, render_rois

    rng = np.random.default_rng(seed)
    w = rng.uniform(1.2, 2.0, N_ROIS)
    table = pd.DataFrame({"x": 5 + rng.uniform(-0.5, 0.5, N_ROIS),
                          "y": 5 + rng.uniform(-0.5, 0.5, N_ROIS), "background": 20.0,
                          "wx": w, "wy": w, "rho": 0.0})  # fmt: skip
    table["amplitude"] = amplitude_of(2000.0, w, w, 0.0)
    np.save(folder / "rois.npy", rng.poisson(render_rois(table, shape=11)).astype(np.float64))


def child(case: str, folder: Path, rounds: int) -> dict:
    """Run one case ``rounds`` times after a warm-up, in this process; wall and CPU seconds."""
    import warnings

    import latentz as lz

    warnings.simplefilter("ignore")
    cam = _camera()
    if case == "fit_rois":
        rois = np.load(folder / "rois.npy")
        lz.fit_rois(rois[:100], device="cpu")
        run = lambda: lz.fit_rois(rois, device="cpu")  # noqa: E731
        units = len(rois)
    else:
        name = {"30": "spots_30", "30-tiff": "spots_30", "500": "spots_500",
                "calibrated": "calibrated", "tracking": "moving"}[case]  # fmt: skip
        frames = np.load(folder / f"{name}.npy")
        source = folder / f"{name}.tif" if case == "30-tiff" else frames
        options: dict = {"camera": cam, "roi_size": 11, "device": "cpu"}
        if case == "calibrated":
            options = {"calibration": lz.Calibration.load(folder / "cal.h5"), "device": "cpu"}
        if case == "tracking":
            options["track"] = True
        # warm up on the same kind of input: a memory-mapped TIFF is a read-only array, which
        # numba compiles (once, cached on disk) apart from a writable one
        lz.localize(source if case == "30-tiff" else frames[:3], **options)
        run = lambda: lz.localize(source, **options)  # noqa: E731
        units = len(frames)
    wall, cpu, rows = [], [], 0
    for _ in range(rounds):
        start, cpu_start = time.perf_counter(), time.process_time()
        rows = len(run())
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    return {"wall": wall, "cpu": cpu, "rows": rows, "units": units}


def run_child(tree: Path, case: str, folder: Path, rounds: int, threads: int | None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = str(threads)
    out = subprocess.run(
        [sys.executable, __file__, "--child", case, "--inputs", str(folder), "--rounds",
         str(rounds)],
        env=env, capture_output=True, text=True, check=True,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def compare(args: argparse.Namespace) -> None:
    started = machine()
    trees = {"before": Path(args.before).resolve(), "after": AFTER}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        make_inputs(folder, args.frames, args.cases)
        for case in args.cases:
            got = {"before": [], "after": [], "cpu_before": [], "cpu_after": []}
            n_rows = {}
            for _ in range(args.turns):  # the trees take turns
                for name, tree in trees.items():
                    result = run_child(tree, case, folder, args.rounds, args.threads)
                    got[name] += [result["units"] / w for w in result["wall"]]
                    got[f"cpu_{name}"] += [result["units"] / c for c in result["cpu"]]
                    n_rows[name] = result["rows"]
            unit = "ROIs/s" if case == "fit_rois" else "frames/s"
            ratio = np.median(got["after"]) / np.median(got["before"])
            rows.append({
                "case": case, "unit": unit, "before": spread(got["before"]),
                "after": spread(got["after"]), "after / before": round(float(ratio), 2),
                "after per CPU s": spread(got["cpu_after"]),
                "before per CPU s": spread(got["cpu_before"]),
                "rows before / after": f"{n_rows['before']} / {n_rows['after']}",
            })  # fmt: skip
            print(rows[-1], flush=True)
    notes = (
        f"2048 x 2048 uint16 frames, {args.frames} per run; {args.rounds} rounds per child "
        f"process after a warm-up, {args.turns} child(ren) per tree taking turns, "
        f"{args.threads or 'all'} thread(s) each; median "
        f"(min-max) over all rounds. `before`: {trees['before']}. The target is {PAPER_HZ} Hz; "
        "'per CPU s' divides by the CPU time of all threads (what a loaded machine leaves)."
    )
    name = "bench_camera_rate"
    if list(args.cases) != list(CASES):  # a subset of the cases keeps its own file
        name += "_" + "_".join(c.replace("-", "") for c in args.cases)
    if args.threads is not None:
        name += f"_{args.threads}thread"
    write_results(f"{name}.md", "`lz.localize` on 2048 x 2048 uint16 camera frames",
                  started, notes, pd.DataFrame(rows).to_markdown(index=False))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="src folder of the tree to compare with")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--turns", type=int, default=1, help="child processes per tree")
    parser.add_argument("--threads", type=int, help="numba threads per child (default: all)")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    parser.add_argument("--inputs", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.inputs, args.rounds)))
    elif args.before is None:
        parser.error("give --before: the src folder of the tree to compare with")
    else:
        compare(args)


if __name__ == "__main__":
    main()

"""Benchmark: the simulator. A calibration dataset of 300 particles x 81 planes in 16 stacks of
512 x 512 px (target: under 60 s on 2 cores) and the quick gear movie, each timed over several
rounds after one small warm-up (numba compilation is not what is measured). Prints and writes
``benchmarks/results/bench_simulate.md``: wall and CPU seconds, median and range over the rounds.

Run: ``python benchmarks/bench_simulate.py [--rounds 3] [--quick]`` (``--quick``: 30 particles in
4 stacks, 2 rounds, to check that it works).
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from _rounds import machine, spread, time_rounds, write_results

from latentz.simulate import calibration_dataset, gear_movie


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--stacks", type=int, default=16)
    parser.add_argument("--quick", action="store_true", help="30 particles, 4 stacks, 2 rounds")
    args = parser.parse_args()
    if args.quick:
        args.particles, args.stacks, args.rounds = 30, 4, 2
    started = machine()
    calibration_dataset(
        n_particles=2, z_nm=np.zeros(3), n_stage_positions=1, frame_shape=(64, 64), min_spacing_px=5
    )
    steps = {
        f"calibration_dataset({args.particles} particles x 81 planes, {args.stacks} stacks of "
        "512 x 512)": lambda: calibration_dataset(
            n_particles=args.particles, n_stage_positions=args.stacks, seed=1
        ),
        "gear_movie(quick=True)": lambda: gear_movie(quick=True),
    }
    rows = []
    for label, step in steps.items():
        wall, cpu = time_rounds(step, args.rounds)
        rows.append(
            {
                "step": label,
                "wall s, median (min–max)": spread(wall),
                "CPU s, median (min–max)": spread(cpu),
                "rounds": args.rounds,
            }
        )
    table = pd.DataFrame(rows)
    print(table.to_string(index=False))
    write_results(
        "bench_simulate.md",
        "Simulator speed",
        started,
        "Seconds per round after a small warm-up; target for 300 particles x 81 planes: under "
        "60 s wall on 2 cores.",
        table.to_markdown(index=False),
        quick=args.quick,
    )


if __name__ == "__main__":
    main()

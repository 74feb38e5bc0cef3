"""Benchmark: Monte Carlo motion uncertainty at the paper's scale (Supp. Note 2).

10,000 simulations x 2,000 motion cycles x 28 particles (target: under 2 minutes on 2 cores),
and the rigid-motion fit it starts from, each timed over several rounds after one warm-up (numba
compilation is not what is measured). Prints and writes ``benchmarks/results/bench_motion.md``:
median and range over the rounds.

Run: ``python benchmarks/bench_motion.py [--rounds 5] [--quick]`` (``--quick``: 1,000
simulations, 3 rounds, to check that it works).
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from _rounds import machine, spread, time_rounds, write_results

from latentz.motion.rigid import rigid_motion
from latentz.motion.uncertainty import motion_uncertainty
from latentz.simulate.gear_motion import gear_trajectory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-sim", type=int, default=10_000)
    parser.add_argument("--n-cycles", type=int, default=2_000)
    parser.add_argument("--n-particles", type=int, default=28)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="1,000 simulations, 3 rounds")
    args = parser.parse_args()
    if args.quick:
        args.n_sim, args.rounds = 1_000, 3
    started = machine()

    truth = gear_trajectory(args.n_cycles, n_particles=args.n_particles, seed=1)
    rng = np.random.default_rng(2)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0.0, 2.0, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0.0, 80.0, len(tracks))

    motion_uncertainty(tracks.query("frame < 3"), n_sim=10)  # compile the numba kernel
    motion = rigid_motion(tracks)
    fit_s, fit_cpu = time_rounds(lambda: rigid_motion(tracks), args.rounds)
    mc_s, mc_cpu = time_rounds(
        lambda: motion_uncertainty(tracks, motion, n_sim=args.n_sim, seed=0), args.rounds
    )
    size = f"{args.n_cycles} transitions x {args.n_particles} particles"
    table = pd.DataFrame(
        {
            "step": ["rigid_motion", "motion_uncertainty"],
            "size": [size, f"{args.n_sim} simulations x {size}"],
            "wall s, median (min–max)": [spread(fit_s, 2), spread(mc_s)],
            "CPU s, median (min–max)": [spread(fit_cpu, 2), spread(mc_cpu)],
            "rounds": [args.rounds, args.rounds],
        }
    )
    print(table.to_string(index=False))
    write_results(
        "bench_motion.md",
        "Monte Carlo motion uncertainty",
        started,
        "Seconds per round after one warm-up; target for the Monte Carlo at the "
        "paper's scale (10,000 x 2,000 x 28): under 120 s on 2 cores.",
        table.to_markdown(index=False),
        quick=args.quick,
    )


if __name__ == "__main__":
    main()

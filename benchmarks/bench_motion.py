"""Benchmark: Monte Carlo motion uncertainty at the paper's scale (Supp. Note 2).

10,000 simulations x 2,000 motion cycles x 28 particles must finish in under 2 minutes on 2 cores.
Run: ``python benchmarks/bench_motion.py [--n-sim N] [--n-cycles N]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from latentz.motion.rigid import rigid_motion
from latentz.motion.uncertainty import motion_uncertainty
from latentz.simulate.gear_motion import gear_trajectory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n-sim", type=int, default=10_000)
    parser.add_argument("--n-cycles", type=int, default=2_000)
    parser.add_argument("--n-particles", type=int, default=28)
    args = parser.parse_args()

    truth = gear_trajectory(args.n_cycles, n_particles=args.n_particles, seed=1)
    rng = np.random.default_rng(2)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0.0, 2.0, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0.0, 80.0, len(tracks))

    motion_uncertainty(tracks.query("frame < 3"), n_sim=10)  # compile the numba kernel
    start = time.perf_counter()
    motion = rigid_motion(tracks)
    fit_s = time.perf_counter() - start
    start = time.perf_counter()
    table = motion_uncertainty(tracks, motion, n_sim=args.n_sim, seed=0)
    mc_s = time.perf_counter() - start
    print(
        f"rigid_motion: {args.n_cycles} transitions x {args.n_particles} particles: {fit_s:.2f} s"
    )
    print(
        f"motion_uncertainty: {args.n_sim} simulations x {args.n_cycles} transitions x "
        f"{args.n_particles} particles: {mc_s:.1f} s (limit 120 s)"
    )
    print(table.to_string())
    print({k: np.round(v, 4).tolist() for k, v in table.attrs.items() if k != "n_sim"})


if __name__ == "__main__":
    main()

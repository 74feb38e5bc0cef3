"""Benchmark: calibration of 1000 particles x 121 planes, fitting included (target < 30 s
on 2 cores), timed over several rounds after one warm-up on a small stack.

Four stacks (stage positions) of 121 planes x 512 x 512 pixels, each with 250 astigmatic
Gaussian particles on a 30 px grid, Poisson noise and read noise, are rendered first (not timed);
then ``calibrate`` runs detection, one ``fit_rois`` batch per stack (30,250 ROIs of 21 x 21 px),
the local models of all particles as arrays, culling and tilt removal. Prints and writes
``benchmarks/results/bench_calibrate.md``: wall and CPU seconds, median and range over the rounds.

Run: ``python benchmarks/bench_calibrate.py [--particles N] [--planes N] [--rounds 5] [--quick]``
(``--quick``: 250 particles, 2 rounds, to check that it works).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd
from _rounds import machine, spread, time_rounds, write_results

from latentz.calibration.workflow import calibrate
from latentz.camera import Camera
from latentz.fit import render_rois

ROI = 21
SPACING = 30


def _stacks(n_particles: int, z_nm: np.ndarray, camera: Camera, seed: int = 0):
    rng = np.random.default_rng(seed)
    per_stack = 250
    n_stacks = int(np.ceil(n_particles / per_stack))
    side = int(np.ceil(np.sqrt(per_stack)))
    size = side * SPACING + 2 * ROI
    stacks = []
    for _ in range(n_stacks):
        k = min(per_stack, n_particles - len(stacks) * per_stack)
        cells = rng.choice(side * side, k, replace=False)
        centre = np.stack([cells % side, cells // side], axis=1) * SPACING + ROI
        centre = centre + rng.uniform(-0.5, 0.5, centre.shape)
        z_f = rng.uniform(-200, 200, k)
        u = z_nm[None, :] - z_f[:, None]
        s1 = 1.5 * np.sqrt(1 + ((u - 500) / 1200) ** 2)
        s2 = 1.5 * np.sqrt(1 + ((u + 500) / 1200) ** 2)
        w = np.sqrt((s1**2 + s2**2) / 2)
        rho = (s1**2 - s2**2) / (s1**2 + s2**2)
        corner = np.floor(centre).astype(int) - ROI // 2
        params = np.stack(
            [
                np.broadcast_to((centre[:, 0] - corner[:, 0])[:, None], u.shape),
                np.broadcast_to((centre[:, 1] - corner[:, 1])[:, None], u.shape),
                5e4 / (2 * np.pi * s1 * s2),
                np.zeros_like(u),
                w,
                w,
                rho,
            ],
            axis=-1,
        ).reshape(-1, 7)
        rois = render_rois(params, shape=ROI).reshape(k, z_nm.size, ROI, ROI)
        frames = np.full((z_nm.size, size, size), 20.0)
        for p in range(k):  # non-overlapping ROIs: plain slices
            r, c = corner[p, 1], corner[p, 0]
            frames[:, r : r + ROI, c : c + ROI] += rois[p]
        counts = rng.poisson(frames) + rng.normal(0, camera.readnoise, frames.shape)
        stacks.append(np.clip(counts / camera.gain + camera.offset, 0, 65535).astype(np.uint16))
    return stacks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--planes", type=int, default=121)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="250 particles, 2 rounds")
    args = parser.parse_args()
    if args.quick:
        args.particles, args.rounds = 250, 2
    started = machine()
    camera = Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=130.0)
    z_nm = np.linspace(-3000.0, 3000.0, args.planes)
    start = time.perf_counter()
    stacks = _stacks(args.particles, z_nm, camera)
    print(
        f"rendered {len(stacks)} stacks of {stacks[0].shape}: {time.perf_counter() - start:.1f} s"
    )
    # warm the numba cache (compilation is not what is being measured)
    calibrate(stacks[0][:, :80, :80], z_nm, camera=camera, field_model="nearest", roi_size=ROI)
    offsets = np.array([[i * stacks[0].shape[2], 0] for i in range(len(stacks))])
    results = []

    def step() -> None:  # keeps only the latest calibration
        results[:] = [
            calibrate(
                stacks,
                z_nm,
                camera=camera,
                field_model="nearest",
                roi_size=ROI,
                stage_offsets_px=offsets,
            )
        ]

    wall, cpu = time_rounds(step, args.rounds)
    particles = results[-1].particles
    table = pd.DataFrame(
        {
            "step": [f"calibrate: {len(particles)} particles x {z_nm.size} planes"],
            "wall s, median (min–max)": [spread(wall)],
            "CPU s, median (min–max)": [spread(cpu)],
            "rounds": [args.rounds],
        }
    )
    print(table.to_string(index=False))
    write_results(
        "bench_calibrate.md",
        "Calibration speed",
        started,
        "Detection, fitting (21 x 21 px ROIs), local models, culling and tilt, field model "
        f"'nearest'; target under 30 s on 2 cores for 1000 x 121. Culled "
        f"{particles['culled'].mean():.1%}; mean σ_z(ρ_A) "
        f"{np.nanmean(particles['sigma_z_rho_A']):.1f} nm.",
        table.to_markdown(index=False),
        quick=args.quick,
    )


if __name__ == "__main__":
    main()

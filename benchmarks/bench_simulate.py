"""Time the simulator: a calibration dataset of 300 particles x 81 planes (target: < 60 s on
2 cores), and the quick gear movie. Run: python benchmarks/bench_simulate.py"""

from __future__ import annotations

import time

import numpy as np

from latentz.simulate import calibration_dataset, gear_movie


def _timed(label: str, func):
    start = time.perf_counter()
    cpu = time.process_time()
    result = func()
    print(
        f"{label}: {time.perf_counter() - start:.1f} s wall, {time.process_time() - cpu:.1f} s CPU"
    )
    return result


def main() -> None:
    calibration_dataset(
        n_particles=2, z_nm=np.zeros(3), n_stage_positions=1, frame_shape=(64, 64), min_spacing_px=5
    )
    data = _timed(
        "calibration_dataset(300 particles x 81 planes, 16 stacks of 512 x 512)",
        lambda: calibration_dataset(n_particles=300, n_stage_positions=16, seed=1),
    )
    n_planes = data.z_nm.size
    print(f"  {len(data.truth)} particles, {n_planes} planes, {len(data.stacks)} stacks")
    _timed("gear_movie(quick=True)", lambda: gear_movie(quick=True))


if __name__ == "__main__":
    main()

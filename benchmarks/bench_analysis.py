"""Benchmark: rendering, drift correction and FRC on simulated data of known truth, the figures
the tests check and the time each step takes.

A 10^4-frame movie of 2000 blinking emitters (1 % duty, 10 nm / 25 nm precision) and 4 beads
with a known drift (linear plus a slow oscillation, 100 nm in x, y and 50 nm in z) for RCC and
fiducials; rings of random diameter for rendering; uniform emitters of random precision for FRC.
Prints and writes ``benchmarks/results/bench_analysis.md``.

Run: ``python benchmarks/bench_analysis.py [--seeds 2]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from _rounds import machine, spread, time_rounds, write_results

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "analysis"))
from structures import blinking_emitters, fiducials, known_drift, rings  # noqa: E402

import latentz as lz  # noqa: E402


def _drift_rows(seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    still = pd.concat(
        [
            blinking_emitters(
                rng, n_emitters=2000, n_frames=10_000, p_on=0.01, field_nm=10_000,
                precision_nm=10.0,
            ),
            fiducials(rng, n_beads=4, n_frames=10_000, field_nm=10_000, precision_nm=3.0),
        ],
        ignore_index=True,
    )  # fmt: skip
    truth = known_drift(still["frame"].to_numpy(), rng)
    moved = still.copy()
    for axis, column in enumerate(("x_nm", "y_nm", "z_nm")):
        moved[column] += truth[:, axis]
    emitters = moved["emitter"] >= 0
    rows = []
    for method in ("rcc", "fiducials"):
        out = {}
        wall, _ = time_rounds(
            lambda m=method, o=out: o.update(
                t=lz.correct_drift(moved, method=m, segment_frames=500)
            ),
            1,
        )
        fixed = out["t"]
        error = pd.DataFrame(fixed[["drift_x_nm", "drift_y_nm", "drift_z_nm"]].to_numpy() - truth)
        error = error.groupby(fixed["frame"].to_numpy()).first().to_numpy()
        rms = np.sqrt(np.mean((error - error.mean(axis=0)) ** 2, axis=0))
        rows.append(
            {
                "seed": seed,
                "method": method,
                "rms x, y, z (nm)": ", ".join(f"{v:.2f}" for v in rms),
                "FRC drifted / corrected / drift-free (nm)": " / ".join(
                    f"{lz.frc(t[emitters], pixel_nm=5.0).resolution_nm:.1f}"
                    for t in (moved, fixed, still)
                ),
                "time (s)": f"{wall[0]:.1f}",
                "localizations": len(moved),
            }
        )
        print(rows[-1])
    return rows


def _ring_row(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    diameter, precision = rng.uniform(150, 300), rng.uniform(4, 10)
    locs, centres = rings(
        rng, n_rings=8, diameter_nm=diameter, precision_nm=precision, per_ring=400, field_nm=4000
    )
    out = {}
    wall, _ = time_rounds(
        lambda: out.update(rgb=lz.render(locs, pixel_nm=5.0, extent=(0, 4000, 0, 4000))), 1
    )
    side = int(np.ceil(4000 / 5.0)) + 1
    bright = out["rgb"][:side, :side].max(axis=2).astype(float)
    rows, cols = np.indices(bright.shape)
    found = []
    for cx, cy in centres:
        r = np.hypot((cols + 0.5) * 5 - cx, (rows + 0.5) * 5 - cy)
        near = r < 0.8 * diameter
        found.append(2 * np.sum(bright[near] * r[near]) / np.sum(bright[near]))
    worst = np.max(np.abs(np.array(found) / diameter - 1))
    return {
        "seed": seed,
        "diameter (nm)": f"{diameter:.1f}",
        "precision (nm)": f"{precision:.1f}",
        "worst ring error (%)": f"{100 * worst:.2f}",
        "render time (s)": f"{wall[0]:.2f}",
    }


def _frc_row(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    sigma, k = rng.uniform(6, 25), int(rng.integers(1, 4))
    where = rng.uniform(0, 8000, (20_000, 2))
    emitter = np.repeat(np.arange(20_000), 2 * k)
    frame = 2 * rng.integers(0, 5000, emitter.size) + np.tile(np.repeat([0, 1], k), 20_000)
    xy = where[emitter] + rng.normal(0, sigma, (emitter.size, 2))
    locs = pd.DataFrame({"frame": frame, "x_nm": xy[:, 0], "y_nm": xy[:, 1]})
    out = {}
    wall, _ = time_rounds(lambda: out.update(r=lz.frc(locs, pixel_nm=5.0, split="odd_even")), 1)
    expected = 2 * np.pi * sigma / np.sqrt(np.log(6 * k + 1))
    return {
        "seed": seed,
        "sigma (nm)": f"{sigma:.1f}",
        "K per half": k,
        "expected (nm)": f"{expected:.1f}",
        "FRC (nm)": f"{out['r'].resolution_nm:.1f}",
        "ratio": f"{out['r'].resolution_nm / expected:.3f}",
        "time (s)": f"{wall[0]:.2f}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2, help="drift movies (rings, FRC: 2x)")
    args = parser.parse_args()
    started = machine()
    drift = pd.DataFrame([r for s in range(11, 11 + args.seeds) for r in _drift_rows(s)])
    ring = pd.DataFrame([_ring_row(s) for s in range(2 * args.seeds)])
    resolution = pd.DataFrame([_frc_row(s) for s in range(2 * args.seeds)])
    ratios = resolution["ratio"].astype(float)
    notes = (
        "Drift: RMS over frames of (removed - true drift), a constant offset removed; FRC of the "
        "blinking emitters (beads left out), blocks of frames. Rings: brightness-weighted mean "
        "radius of the rendered x-y view about each true centre. FRC: emitters localized K times "
        "in even and K times in odd frames; expected 2 pi sigma / sqrt(ln(6K + 1)); ratio "
        f"{spread(ratios, 3)}. Timings: one round each on a shared, loaded 2-core machine."
    )
    table = "\n\n".join(t.to_markdown(index=False) for t in (drift, ring, resolution))
    print(table)
    write_results("bench_analysis.md", "Rendering, drift and FRC against truth", started, notes,
                  table)  # fmt: skip


if __name__ == "__main__":
    main()

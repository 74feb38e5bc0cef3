"""Molecules at the frame's edge against truth: found, good, and whether their 1σ holds.

For ``--microscopes`` random astigmatic microscopes (:func:`latentz.simulate.molecules.
random_microscope`, seeds from ``--seed``), each calibrated with defaults on its own simulated
100 nm beads (:func:`latentz.validation.molecules.bead_calibration`), ``--frames`` frames of
96 x 96 px hold three molecules along each edge, 0–7.5 px from it, and four inside
(:func:`latentz.simulate.molecules.place_edge_molecules`: 3,000–10,000 photons, z within
±400 nm). They are localized with defaults (:func:`latentz.validation.molecules.edge_errors`):
the errors across the nearest edge, along it and in z (one z offset removed) against the
reported 1σ, by distance to the edge, per microscope and over all (one offset per axis, the
inner molecules' median error, removed). ``--no-truncation`` sets the slopes of
:data:`latentz.localization.edges.TRUNCATION` to zero, to show the fit's own errors.
Writes ``results/bench_edges.md`` (``bench_edges_no_truncation.md``).

Run: ``python benchmarks/bench_edges.py``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_verdicts import markdown

from latentz.localization import edges
from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import bead_calibration, edge_errors

BANDS = ((0.0, 1.0), (1.0, 3.0), (3.0, 7.5), (7.5, np.inf))


def summary(errors: pd.DataFrame, label: str) -> list[dict]:
    """One row per distance band: molecules, found, good, edge, 1σ coverage and RMS."""
    out = []
    for low, high in BANDS:
        band = errors[(errors["distance_px"] >= low) & (errors["distance_px"] < high)]
        seen = band[band["found"] & np.isfinite(band["z_nm"])]
        row = {
            "microscope": label,
            "distance px": "inside" if np.isinf(high) else f"{low:g}–{high:g}",
            "molecules": len(band),
            "found": band["found"].mean(),
            "good": seen["good"].mean(),
            "edge": seen["edge"].mean(),
        }
        for axis in ("across", "along", "z"):
            error, sigma = seen[f"{axis}_nm"], seen[f"{axis}_err_nm"]
            row[f"{axis} 1σ covers"] = float(np.mean(np.abs(error) < sigma))
        row["across RMSE nm"] = float(np.sqrt(np.mean(seen["across_nm"] ** 2)))
        row["z RMSE nm"] = float(np.sqrt(np.mean(seen["z_nm"] ** 2)))
        row["median σ_z nm"] = float(np.median(seen["z_err_nm"]))
        out.append(row)
    return out


def microscope_parser(doc: str, frames: int) -> argparse.ArgumentParser:
    """The options of the benchmarks over random microscopes: how many, the first's seed (121:
    none of those the truncation error was fitted on) and frames per microscope."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--microscopes", type=int, default=6)
    parser.add_argument("--seed", type=int, default=121, help="seed of the first microscope")
    parser.add_argument("--frames", type=int, default=frames)
    return parser


def main() -> None:
    parser = microscope_parser(__doc__, frames=40)
    parser.add_argument("--no-truncation", action="store_true")
    args = parser.parse_args()
    if args.no_truncation:
        edges.TRUNCATION = {term: (0.0, *rest) for term, (_, *rest) in edges.TRUNCATION.items()}
    started, start = machine(), time.perf_counter()
    rows, every = [], []
    for seed in range(args.seed, args.seed + args.microscopes):
        rng = np.random.default_rng(seed)
        microscope = random_microscope(rng)
        calibration = bead_calibration(microscope, seed)
        errors = edge_errors(microscope, calibration, rng, n_frames=args.frames)
        rows += summary(errors, f"{seed} (ROI {calibration.roi_size} px)")
        every.append(errors)
    rows += summary(pd.concat(every, ignore_index=True), "all")
    notes = (
        "1σ covers: share of the found molecules whose error lies within the reported 1σ "
        "(68.3 % for a right 1σ; 2 binomial SE over 100 molecules: ±9 %, over 400: ±4.7 %). "
        f"Truncation terms (slope, power, width factor): {edges.TRUNCATION}. "
        f"Took {time.perf_counter() - start:.0f} s on a loaded machine."
    )
    table = markdown(pd.DataFrame(rows))
    name = "bench_edges_no_truncation.md" if args.no_truncation else "bench_edges.md"
    write_results(name, "Molecules at the frame's edge", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

"""Crowded frames against truth: errors and their reported 1σ by density, single and pair rows.

Each of ``--microscopes`` random astigmatic microscopes (seeds ``--first`` on,
:func:`latentz.simulate.molecules.random_microscope`) is calibrated with defaults on a simulated
stack of six 100 nm beads (:func:`latentz.validation.molecules.bead_calibration`). Its test
frames (:func:`latentz.simulate.molecules.molecule_frames`, 128 x 128 px) hold point molecules of
300–10,000 photons (log-uniform) at uniform positions and depths within ±600 nm, at 0.2, 0.5, 1
and 2 per µm², localized with the calibration and defaults. A localization is correct when the
challenge's one-to-one matching pairs it with a true molecule within 250 nm laterally and
500 nm axially, one z offset removed (:func:`latentz.validation.challenge.offset_pairs`); its
errors are against where the simulation put that molecule.

Per density: molecules, recall (correct / molecules), the share of correct rows that are
``good``, and for the good one-emitter rows and the good rows of two-emitter fits: their number,
z and lateral RMSE (nm) and the share whose x, y, z error lies within its reported 1σ. Then the
good one-emitter rows by the distance (px) from their molecule to its nearest other molecule,
all of them and split by whether the row's ROI overlaps another detection's (the rows whose errors
the crowding factor scales): where their errors come from. Writes ``results/bench_crowding.md``.

Run: ``python benchmarks/bench_crowding.py [--microscopes 2] [--first 0] [--frames 10]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_pairs import DENSITIES, FIELD, markdown
from scipy.spatial import cKDTree

from latentz.localization.pairs import crowded
from latentz.simulate.molecules import random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.molecules import bead_calibration, localized_molecules

NEAREST_PX = (0, 2, 3, 4, 6, 10, np.inf)


def nearest_other(truth: pd.DataFrame) -> np.ndarray:
    """Distance (px) from each true molecule to the nearest other one in its frame."""
    points = truth[["x", "y"]].to_numpy(float)
    frame = truth["frame"].to_numpy()
    out = np.full(len(truth), np.inf)
    for f in np.unique(frame):
        rows = np.flatnonzero(frame == f)
        if rows.size > 1:
            out[rows] = cKDTree(points[rows]).query(points[rows], k=2)[0][:, 1]
    return out


def matched(locs: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """One row per correct localization: its errors (nm), reported 1σ (nm), ``good``, ``pair``
    and its molecule's distance to the nearest other molecule (px)."""
    pairs, _ = offset_pairs(truth, locs)
    rows = locs.loc[pairs["locs_row"]]
    out = pd.DataFrame({f"d{a}": pairs[f"d{a}_nm"].to_numpy() for a in "xyz"})
    for a in "xyz":
        out[f"s{a}"] = rows[f"{a}_err_nm"].to_numpy()
    out["good"] = rows["good"].to_numpy(bool)
    out["pair"] = rows["pair"].to_numpy() >= 0
    shares = crowded(locs, int(locs.attrs["roi_size"]))  # as crowding_factor reads it
    out["shares_roi"] = shares[locs.index.get_indexer(pairs["locs_row"])]
    out["nearest_px"] = nearest_other(truth)[truth.index.get_indexer(pairs["truth_row"])]
    return out


def one_microscope(seed: int, n_frames: int) -> list[dict]:
    """Matched rows of every density on one random microscope, with the molecule count."""
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, field_shape=FIELD)
    cal = bead_calibration(microscope, seed, field_shape=FIELD)
    out = []
    for density in DENSITIES:
        locs, truth, _ = localized_molecules(microscope, cal, rng, density_per_um2=density,
                                             n_frames=n_frames, field_shape=FIELD)  # fmt: skip
        out.append({"density /µm²": density, "molecules": len(truth),
                    "rows": matched(locs, truth)})  # fmt: skip
    return out


def errors(rows: pd.DataFrame) -> dict[str, float]:
    """Number, RMSE (nm) and 1σ coverage of x, y, z of ``rows``."""
    out = {"n": len(rows), "z RMSE": np.sqrt(np.mean(rows["dz"] ** 2)),
           "lateral RMSE": np.sqrt(np.mean(rows["dx"] ** 2 + rows["dy"] ** 2))}  # fmt: skip
    for a in "xyz":
        out[f"1σ covers {a}"] = np.mean(np.abs(rows[f"d{a}"]) <= rows[f"s{a}"])
    return out


def by_density(runs: list[dict]) -> pd.DataFrame:
    """Recall, share kept good, and `errors` of good single and pair rows, per density."""
    table = []
    for density in DENSITIES:
        parts = [r for r in runs if r["density /µm²"] == density]
        rows = pd.concat([r["rows"] for r in parts], ignore_index=True)
        good = rows[rows["good"]]
        line = {"density /µm²": density, "molecules": sum(r["molecules"] for r in parts),
                "recall": len(rows) / sum(r["molecules"] for r in parts),
                "good / correct": rows["good"].mean()}  # fmt: skip
        for name, part in (("single", good[~good["pair"]]), ("pair", good[good["pair"]])):
            line.update({f"{name} {k}": v for k, v in errors(part).items()})
        table.append(line)
    return pd.DataFrame(table)


def by_nearest(runs: list[dict]) -> pd.DataFrame:
    """`errors` of the good one-emitter rows by their molecule's nearest other molecule (px),
    and by whether the row's ROI overlaps another detection's (the rows whose errors the
    crowding factor scales, :mod:`latentz.localization.crowding`)."""
    rows = pd.concat([r["rows"] for r in runs], ignore_index=True)
    rows = rows[rows["good"] & ~rows["pair"]]
    bins = pd.cut(rows["nearest_px"], NEAREST_PX)
    table = []
    for b, part in rows.groupby(bins, observed=True):
        table.append({"nearest molecule px": str(b), "ROI overlaps a detection": "any",
                      **errors(part)})  # fmt: skip
        for shares, name in ((True, "yes"), (False, "no")):
            table.append({"nearest molecule px": str(b), "ROI overlaps a detection": name,
                          **errors(part[part["shares_roi"] == shares])})  # fmt: skip
    return pd.DataFrame(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--microscopes", type=int, default=2)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--frames", type=int, default=10)
    args = parser.parse_args()
    started, start = machine(), time.perf_counter()
    seeds = range(args.first, args.first + args.microscopes)
    runs = [run for seed in seeds for run in one_microscope(seed, args.frames)]
    notes = (
        f"Microscopes {list(seeds)} x densities {DENSITIES} /µm², {args.frames} frames of "
        f"{FIELD[0]} x {FIELD[1]} px each. Took {time.perf_counter() - start:.0f} s on a loaded "
        "machine."
    )
    table = markdown(by_density(runs)) + "\n\n" + markdown(by_nearest(runs))
    write_results("bench_crowding.md", "Crowded frames against truth", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

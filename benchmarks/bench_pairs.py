"""Close pairs against truth: recall and RMSE against density, with and without the two-emitter
fit, on simulated single-molecule frames.

Each of ``--microscopes`` random astigmatic microscopes
(:func:`latentz.simulate.molecules.random_microscope`) is calibrated with defaults on a simulated
stack of six 100 nm beads (:func:`latentz.validation.molecules.bead_calibration`). Its test
frames (:func:`latentz.simulate.molecules.molecule_frames`, 128 x 128 px) hold point molecules of
300–10,000 photons (log-uniform) at uniform positions and depths within ±600 nm, at 0.2, 0.5, 1
and 2 per µm². The same frames are localized with the calibration and defaults, once with the
two-emitter fit (``pairs=True``, the default) and once without. A localization is *correct* when
the challenge's one-to-one matching pairs it with a true molecule within 250 nm laterally and
500 nm axially, one z offset removed (:func:`latentz.validation.challenge.offset_pairs`); the
truth is where the simulation put each molecule.

Per density and mode: rows, correct rows, recall (correct / molecules placed) and the Jaccard
index of every row and of the ``good`` rows, lateral and axial RMSE of the correct ones, the
pairs reported and how many of their rows are correct, the share of correct pair rows whose z
lies within its reported 1σ, and the time of ``localize``. Then, on each microscope, molecules
on a 20 px grid (no neighbour within 2 µm): how many are split, which no one should be. Last,
the speed of ``localize`` with and without on the frames of ``bench_localize.py``. Writes
``results/bench_pairs.md``.

Run: ``python benchmarks/bench_pairs.py [--microscopes 4] [--frames 6]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_localize import spots_movie

from latentz.localization import localize
from latentz.simulate.molecules import molecule_frames, place_molecules, random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.molecules import bead_calibration

FIELD = (128, 128)
DENSITIES = (0.2, 0.5, 1.0, 2.0)


def scores(locs: pd.DataFrame, truth: pd.DataFrame) -> dict[str, float]:
    """Counts and errors of one localization table against its truth."""
    matched, _ = offset_pairs(truth, locs)
    good, _ = offset_pairs(truth, locs[locs["good"]])
    rows = locs.loc[matched["locs_row"]]
    in_pair = (rows["pair"] >= 0).to_numpy()
    within = np.abs(matched["dz_nm"].to_numpy()) <= rows["z_err_nm"].to_numpy()
    return {
        "molecules": len(truth),
        "rows": len(locs),
        "correct": len(matched),
        "good rows": int(locs["good"].sum()),
        "good correct": len(good),
        "pair rows": int((locs["pair"] >= 0).sum()),
        "pair rows correct": int(in_pair.sum()),
        "pair z 1σ covers": float(within[in_pair].mean()) if in_pair.any() else np.nan,
        "lateral RMSE nm": float(np.sqrt(np.mean(matched["dx_nm"] ** 2 + matched["dy_nm"] ** 2))),
        "axial RMSE nm": float(np.sqrt(np.mean(matched["dz_nm"] ** 2))),
    }


def isolated_splits(microscope, cal, rng: np.random.Generator, n_frames: int) -> dict:
    """Molecules on a grid 20 px apart (no neighbour within 2 µm), as in the densities' frames
    otherwise: how many are split into pairs, and how many one-emitter rows are ``merged``."""
    centres = np.arange(10.0, FIELD[0] - 9, 20.0)
    x, y = (a.ravel() for a in np.meshgrid(centres, centres))
    n = x.size * n_frames
    molecules = pd.DataFrame({
        "frame": np.repeat(np.arange(n_frames), x.size),
        "x": np.tile(x, n_frames) + rng.uniform(-0.5, 0.5, n),
        "y": np.tile(y, n_frames) + rng.uniform(-0.5, 0.5, n),
        "z_nm": rng.uniform(-600.0, 600.0, n),
        "photons": np.exp(rng.uniform(np.log(300.0), np.log(1e4), n)),
    })  # fmt: skip
    frames, _ = molecule_frames(
        molecules, microscope, n_frames=n_frames, frame_shape=FIELD,
        seed=int(rng.integers(2**31)),
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        locs = localize(frames, calibration=cal)
    return {"molecules": n, "rows": len(locs), "split": int((locs["pair"] >= 0).sum() // 2),
            "merged": int(locs["merged"].sum())}  # fmt: skip


def one_microscope(seed: int, n_frames: int) -> tuple[list[dict], dict]:
    """Scores of every density and mode on one random microscope, and its isolated splits."""
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, field_shape=FIELD)
    cal = bead_calibration(microscope, seed, field_shape=FIELD)
    out = []
    for density in DENSITIES:
        molecules = place_molecules(
            rng, n_frames=n_frames, frame_shape=FIELD, density_per_um2=density,
            pixel_nm=microscope.optics.pixel_size_nm,
        )  # fmt: skip
        frames, truth = molecule_frames(
            molecules, microscope, n_frames=n_frames, frame_shape=FIELD,
            seed=int(rng.integers(2**31)),
        )  # fmt: skip
        for pairs in (False, True):
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the CPU note; the verdicts are in the table
                locs = localize(frames, calibration=cal, pairs=pairs)
            took = time.perf_counter() - start
            out.append({"microscope": seed, "density /µm²": density, "pairs": pairs,
                        "localize s": took, **scores(locs, truth)})  # fmt: skip
    return out, isolated_splits(microscope, cal, rng, n_frames)


def summary(runs: pd.DataFrame) -> pd.DataFrame:
    """Totals over microscopes per density and mode, as recall, Jaccard and RMSE."""
    rows = []
    for (density, pairs), part in runs.groupby(["density /µm²", "pairs"]):
        n, sums = part["molecules"].sum(), part.sum(numeric_only=True)
        weight = part["correct"] / part["correct"].sum()
        rows.append({
            "density /µm²": density, "two-emitter fit": "yes" if pairs else "no",
            "molecules": n, "rows": sums["rows"], "recall": sums["correct"] / n,
            "Jaccard": sums["correct"] / (sums["rows"] + n - sums["correct"]),
            "good recall": sums["good correct"] / n,
            "good Jaccard": sums["good correct"] / (sums["good rows"] + n - sums["good correct"]),
            "lateral RMSE nm": np.sqrt(np.sum(weight * part["lateral RMSE nm"] ** 2)),
            "axial RMSE nm": np.sqrt(np.sum(weight * part["axial RMSE nm"] ** 2)),
            "pair rows": sums["pair rows"], "pair rows correct": sums["pair rows correct"],
            "localize s": sums["localize s"],
        })  # fmt: skip
    return pd.DataFrame(rows)


def speed(n_frames: int = 20, rounds: int = 3) -> pd.DataFrame:
    """Frames/s of ``localize`` with and without the two-emitter fit on the 2048 x 2048 frames
    of ``bench_localize.py`` (30 and 500 Gaussian spots per frame), best of ``rounds``,
    alternating the two so that the machine's load falls on both alike."""
    rows = []
    for per_frame in (30, 500):
        frames = spots_movie(n_frames, per_frame)
        localize(frames[:2])  # compile outside the measurement
        best = {False: np.inf, True: np.inf}
        for _ in range(rounds):
            for pairs in (False, True):
                start = time.perf_counter()
                locs = localize(frames, pairs=pairs)
                best[pairs] = min(best[pairs], time.perf_counter() - start)
        rows.append({"spots per frame": per_frame, "frames": n_frames,
                     "frames/s without": n_frames / best[False],
                     "frames/s with": n_frames / best[True],
                     "pairs split": int((locs["pair"] >= 0).sum() // 2)})  # fmt: skip
    return pd.DataFrame(rows)


def markdown(table: pd.DataFrame) -> str:
    """A markdown table, numbers to 3 significant digits."""
    head = "| " + " | ".join(table.columns) + " |\n|" + "---|" * len(table.columns)
    body = [
        "| " + " | ".join(v if isinstance(v, str) else f"{v:.3g}" for v in row) + " |"
        for row in table.itertuples(index=False)
    ]
    return "\n".join([head, *body])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--microscopes", type=int, default=4)
    parser.add_argument("--frames", type=int, default=6)
    args = parser.parse_args()
    started, start = machine(), time.perf_counter()
    results = [one_microscope(s, args.frames) for s in range(args.microscopes)]
    runs = pd.DataFrame([row for rows, _ in results for row in rows])
    isolated = pd.DataFrame([counts for _, counts in results]).sum()
    correct = runs[runs["pairs"]]
    covers = np.nansum(correct["pair z 1σ covers"] * correct["pair rows correct"]) / max(
        correct["pair rows correct"].sum(), 1
    )
    notes = (
        f"{args.microscopes} random microscopes x densities {DENSITIES} /µm², {args.frames} "
        f"frames of {FIELD[0]} x {FIELD[1]} px each, localized with and without the two-emitter "
        f"fit. z of the correct pair rows lies within its reported 1σ in {covers:.0%} of them. "
        f"Of {isolated['molecules']} isolated molecules (a 20 px grid, the same photons and "
        f"depths), {isolated['split']} were split into pairs and {isolated['merged']} rows "
        "marked merged. "
        f"Took {time.perf_counter() - start:.0f} s on a loaded machine (`localize s`: the time "
        "of localize over all microscopes)."
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU note
        table = markdown(summary(runs)) + "\n\n" + markdown(speed())
    write_results("bench_pairs.md", "Close pairs against truth", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

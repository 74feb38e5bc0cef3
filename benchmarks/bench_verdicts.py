"""The quality verdicts against truth: what share of correct and of wrong localizations each flag
removes, on simulated single-molecule frames.

Each of ``--microscopes`` random astigmatic microscopes
(:func:`latentz.simulate.molecules.random_microscope`) is calibrated with defaults on a simulated
stack of six 100 nm beads (±1 µm in 25 nm steps). Its test frames
(:func:`latentz.simulate.molecules.molecule_frames`, 128 x 128 px) hold point molecules of
300-10,000 photons (log-uniform) at uniform positions over the whole frame and depths within
±600 nm, at each density of 0.2, 0.5, 1 and 2 per µm². ``lz.localize`` runs with the calibration
and defaults only. A localization is *correct* when the challenge's one-to-one matching pairs it
with a true molecule within 250 nm laterally and 500 nm axially (one z offset removed,
:func:`latentz.validation.challenge.correct_rows`); the truth is where the simulation put each
molecule, never a latentz fit.

For each flag: the share of the correct localizations lost when the rows it flags are dropped
(matched afresh: a duplicate's twin may take its place) and the share of the wrong rows it
flags; for the three scored flags (``consistency_chi2`` for ``inconsistent``, ``z_far_p`` for
``out_of_range``, the distance to the nearest fit for ``unresolved``) the same shares at every
threshold, with the threshold in use marked. Then ``good``'s share of the correct localizations
by density, and recall and RMSE of every row and of the good rows by the molecules' distance to
the frame's edge, to their nearest neighbour, and by photons. Writes
``results/bench_verdicts.md`` and ``docs/images/single-molecules-verdicts.png``; ``--cache``
keeps the localizations in a pickle, so thresholds can be tried without localizing again.

Run: ``python benchmarks/bench_verdicts.py [--microscopes 4] [--frames 6] [--cache PATH]``.
"""

from __future__ import annotations

import argparse
import pickle
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from scipy.spatial import cKDTree

from latentz.calibration import Calibration
from latentz.localization import mismatch, quality
from latentz.simulate.molecules import random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.molecules import bead_calibration, localized_molecules, true_positives

FIGURE = Path(__file__).resolve().parents[1] / "docs" / "images" / "single-molecules-verdicts.png"
FIELD = (128, 128)
DENSITIES = (0.2, 0.5, 1.0, 2.0)
FLAGS = ("not_converged", "duplicate", "unresolved", "out_of_range", "inconsistent")


def scored_sets(seed: int, n_frames: int) -> list[tuple]:
    """(localizations, truth, calibration) of one microscope at each density; the
    localizations carry ``correct``, ``microscope`` and ``density``."""
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, field_shape=FIELD)
    cal = bead_calibration(microscope, seed, field_shape=FIELD)
    sets = []
    for density in DENSITIES:
        locs, truth, _ = localized_molecules(
            microscope, cal, rng, density_per_um2=density, n_frames=n_frames, field_shape=FIELD
        )
        sets.append((locs.assign(microscope=seed, density=density), truth, cal))
    return sets


def neighbour_px(locs: pd.DataFrame) -> np.ndarray:
    """Chebyshev distance (px) from each row to the nearest other converged, non-duplicate fit
    of its frame (what ``unresolved`` compares with half the ROI)."""
    out = np.full(len(locs), np.inf)
    usable = (locs["converged"] & ~locs["duplicate"]).to_numpy(bool)
    for _, rows in locs.groupby("frame").indices.items():
        mine = rows[usable[rows]]
        if mine.size < 2:
            continue
        points = locs[["x", "y"]].to_numpy(float)[mine]
        out[mine] = cKDTree(points).query(points, k=2, p=np.inf)[0][:, 1]
    return out


def removed_shares(sets: list) -> pd.DataFrame:
    """Per flag: the share of the correct localizations (those all rows find) lost when the
    rows it flags are dropped, matched afresh (a duplicate's twin may take its place), and the
    share of the wrong rows it flags."""
    everything = true_positives(sets)
    rows = pd.concat([locs for locs, _ in sets], ignore_index=True)
    wrong = ~rows["correct"].to_numpy(bool)
    out = []
    for name in (*FLAGS, "good"):
        if name == "good":
            lost = 1 - true_positives(sets, lambda locs: locs["good"].to_numpy(bool)) / everything
            out.append(
                {
                    "flag": "not good (any flag)",
                    "correct lost": lost,
                    "wrong removed": 1 - rows["good"].to_numpy(bool)[wrong].mean(),
                }
            )
            continue  # fmt: skip
        lost = 1 - true_positives(sets, lambda locs, f=name: ~_flag(locs, f)) / everything
        out.append(
            {"flag": name, "correct lost": lost, "wrong removed": _flag(rows, name)[wrong].mean()}
        )
    return pd.DataFrame(out)


def _flag(rows: pd.DataFrame, name: str) -> np.ndarray:
    if name == "not_converged":
        return ~rows["converged"].to_numpy(bool)
    return rows[name].to_numpy(bool)


def threshold_curve(sets: list, score: str, limit: float, *, below: bool = False) -> pd.DataFrame:
    """Share of the correct localizations lost and of the wrong rows removed when the rows
    whose ``score`` exceeds (``below``: falls short of) each threshold, ``limit`` among them,
    are dropped."""
    everything = true_positives(sets)
    rows = pd.concat([locs for locs, _ in sets], ignore_index=True)
    values = rows[score].to_numpy(float)
    wrong = ~rows["correct"].to_numpy(bool)
    grid = np.nanquantile(values[np.isfinite(values)], np.linspace(0, 1, 41))
    thresholds = np.unique(np.append(grid, limit))
    lost, removed = [], []
    for t in thresholds:
        with np.errstate(invalid="ignore"):
            kept = true_positives(sets, lambda locs, t=t: ~_beyond(locs[score], t, below))
            lost.append(1 - kept / everything)
            removed.append(_beyond(values, t, below)[wrong].mean())
    return pd.DataFrame({"threshold": thresholds, "correct": lost, "wrong": removed})


def _beyond(values, threshold: float, below: bool) -> np.ndarray:
    values = np.asarray(values, float)
    return values < threshold if below else values > threshold


def markdown(table: pd.DataFrame) -> str:
    """``table`` as a markdown table, numbers to three decimals."""
    cells = [[f"{v:.3f}" if isinstance(v, float) else str(v) for v in row] for row in table.values]
    lines = ["| " + " | ".join(map(str, table.columns)) + " |", "|" + "---|" * table.shape[1]]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])


def figure(sets: list, shares: pd.DataFrame) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    for score, limit, below, label in (
        ("consistency_chi2", quality.CHI2_LIMIT, False, "inconsistent: consistency χ²"),
        ("z_far_p", quality.FAR_LIMIT, False, "out of range: chance z is 500 nm off"),
        ("neighbour_px", quality.UNRESOLVED_PX, True, "unresolved: neighbour distance"),
    ):
        curve = threshold_curve(sets, score, limit, below=below)
        (line,) = ax.plot(100 * curve["correct"], 100 * curve["wrong"], ".-", label=label)
        at = int(np.flatnonzero(curve["threshold"] == limit)[0])
        ax.plot(100 * curve["correct"].iloc[at], 100 * curve["wrong"].iloc[at], "o", ms=9,
                color=line.get_color())  # fmt: skip
    ax.axvline(2.0, color="0.6", ls=":", label="2 % of the correct ones")
    ax.set(xlabel="correct localizations lost (%)", ylabel="wrong localizations removed (%)",
           title="Threshold trade-off (big dot: the threshold in use)")  # fmt: skip
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlim(0.0, 100.0)
    ax.legend(fontsize=8)
    ax = axes[1]
    y = np.arange(len(shares))
    ax.barh(y - 0.2, 100 * shares["correct lost"], 0.4, label="correct lost")
    ax.barh(y + 0.2, 100 * shares["wrong removed"], 0.4, label="wrong removed")
    ax.set_yticks(y, [s.replace("_", " ") for s in shares["flag"]])
    ax.set(xlabel="% of the localizations", title="What each flag removes")
    ax.legend(fontsize=8)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=110)


def by_density(sets: list) -> pd.DataFrame:
    """Per density: rows, correct rows, and the share of them that ``good`` keeps (matched
    afresh)."""
    out = []
    for density in DENSITIES:
        mine = [(locs, t) for locs, t in sets if locs["density"].iloc[0] == density]
        everything = true_positives(mine)
        good = true_positives(mine, lambda locs: locs["good"].to_numpy(bool))
        rows = sum(len(locs) for locs, _ in mine)
        out.append({"density /µm²": density, "rows": rows, "correct": everything,
                    "good keeps of correct": good / everything})  # fmt: skip
    return pd.DataFrame(out)


def breakdown(sets: list, column: str, edges: tuple) -> pd.DataFrame:
    """Recall, RMSE and the share of z errors within the reported 1σ, of every row and of the
    ``good`` rows, by the molecules' ``column`` (``edge_px``: distance to the frame's edge;
    ``neighbour_nm``: to the nearest other molecule of the frame; ``photons``), binned at
    ``edges``."""
    parts = []
    for locs, truth in sets:
        truth = truth.assign(edge_px=_edge_px(truth), neighbour_nm=_neighbour_nm(truth))
        for name, rows in (("all", locs), ("good", locs[locs["good"].to_numpy(bool)])):
            pairs = offset_pairs(truth, rows)[0].join(rows["z_err_nm"], on="locs_row")
            found = truth.join(
                pairs.set_index("truth_row")[["dx_nm", "dy_nm", "dz_nm", "z_err_nm"]]
            )
            parts.append(found.assign(rows=name))
    table = pd.concat(parts, ignore_index=True)
    table["bin"] = pd.cut(table[column], edges)
    out = []
    for (interval, name), g in table.groupby(["bin", "rows"], observed=True):
        hit = g["dz_nm"].notna()
        out.append({
            column: str(interval), "rows": name, "molecules": len(g),
            "recall": hit.mean(),
            "lateral RMSE nm": np.sqrt(np.mean(g["dx_nm"][hit] ** 2 + g["dy_nm"][hit] ** 2)),
            "axial RMSE nm": np.sqrt(np.mean(g["dz_nm"][hit] ** 2)),
            "z 1σ covers": np.mean(np.abs(g["dz_nm"][hit]) <= g["z_err_nm"][hit]),
        })  # fmt: skip
    return pd.DataFrame(out)


def _edge_px(truth: pd.DataFrame) -> np.ndarray:
    x, y = truth["x"].to_numpy(float), truth["y"].to_numpy(float)
    return np.minimum.reduce([x + 0.5, y + 0.5, FIELD[1] - 0.5 - x, FIELD[0] - 0.5 - y])


def _neighbour_nm(truth: pd.DataFrame) -> np.ndarray:
    out = np.full(len(truth), np.inf)
    for _, rows in truth.groupby("frame").indices.items():
        if rows.size > 1:
            points = truth[["x_nm", "y_nm"]].to_numpy(float)[rows]
            out[rows] = cKDTree(points).query(points, k=2)[0][:, 1]
    return out


def localized(seeds: range, n_frames: int, cache: Path | None) -> list:
    """The sets of :func:`scored_sets`, their verdicts made afresh by the current
    :mod:`latentz.localization.quality`; with ``cache``, the localizations are read from (or
    written to) that pickle, so thresholds can be tried without localizing again."""
    if cache is not None and cache.exists():
        with open(cache, "rb") as f:
            raw = pickle.load(f)
    else:
        raw = [item for s in seeds for item in scored_sets(s, n_frames)]
        if cache is not None:
            with open(cache, "wb") as f:
                pickle.dump(raw, f)
    sets = []
    for locs, truth, cal in raw:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            judged = mismatch.check_calibration_fits(verdicts(locs, cal), cal)
        sets.append((judged.assign(neighbour_px=neighbour_px(judged)), truth))
    return sets


def verdicts(locs: pd.DataFrame, cal: Calibration) -> pd.DataFrame:
    """``locs`` (a ``localize`` table) with its verdicts made afresh by the current
    :mod:`latentz.localization.quality` as ``localize`` makes them: on the errors before the
    crowding factor (:mod:`latentz.localization.crowding`), which ``cal.apply`` gives again; the
    table keeps its reported errors."""
    judged = quality.assess(cal.apply(locs), cal)
    columns = [c for c in quality.QUALITY_COLUMNS if c in judged]
    return locs.drop(columns=[c for c in columns if c in locs]).join(judged[columns])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--microscopes", type=int, default=4)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--cache", type=Path, default=None, help="pickle of the localizations")
    args = parser.parse_args()
    started, start = machine(), time.perf_counter()
    sets = localized(range(args.microscopes), args.frames, args.cache)
    shares = removed_shares(sets)
    figure(sets, shares)
    n_rows = sum(len(locs) for locs, _ in sets)
    notes = (
        f"{args.microscopes} random microscopes x densities {DENSITIES} /µm², "
        f"{args.frames} frames of {FIELD[0]} x {FIELD[1]} px each; {n_rows} localizations. "
        f"Thresholds: CHI2_LIMIT {quality.CHI2_LIMIT:g}, CURVE_SCATTER "
        f"{quality.CURVE_SCATTER:g}, FAR_LIMIT {quality.FAR_LIMIT:.4f}, UNRESOLVED_PX "
        f"{quality.UNRESOLVED_PX:g}. Took {time.perf_counter() - start:.0f} s on a loaded machine."
    )
    tables = [markdown(shares), markdown(by_density(sets))]
    for column, edges in (
        ("edge_px", (0, 2, 5, 10, np.inf)),
        ("neighbour_nm", (0, 300, 600, 1000, np.inf)),
        ("photons", (300, 1000, 3000, 10000)),
    ):
        tables.append(markdown(breakdown(sets, column, edges)))
    table = "\n\n".join(tables)
    write_results("bench_verdicts.md", "Quality verdicts against truth", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

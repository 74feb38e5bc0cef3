"""What windows cost `fit_arrays`: whole ROIs with and without ``windows``, and clipped ones.

``--n`` simulated 11 x 11 px ROIs of eq. 1 (the ROIs of ``tests/fit``'s truth tables: centred
spots of 1,000–100,000 photons, widths 1–3 px) are fitted on ``--threads`` threads: without
windows, with every window whole (the path of a movie's interior ROIs), and with each ROI
clipped as at a frame's edge, 0–5 columns cut off its left side. Timings are the best of
``--rounds`` interleaved rounds. Writes ``results/bench_fit_windows.md``.

Run: ``python benchmarks/bench_fit_windows.py``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_verdicts import markdown

from latentz.fit import fit_arrays

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fit"))
from fit_truth import noisy_rois, truth_table  # noqa: E402

SIZE = 11


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20_000)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    numba.set_num_threads(args.threads)
    started = machine()
    rois = noisy_rois(truth_table(args.n, SIZE, seed=1), SIZE, seed=2)
    cut = np.arange(args.n) % 6
    clipped = np.column_stack([np.zeros(args.n), np.full(args.n, SIZE), cut, np.full(args.n, SIZE)])
    whole = np.tile([0, SIZE, 0, SIZE], (args.n, 1))
    cases = {
        "no windows": None,
        "whole windows": whole,
        "clipped windows (0–5 columns cut)": clipped.astype(int),
    }
    for windows in cases.values():  # compile and warm up
        fit_arrays(rois[:200], windows=None if windows is None else windows[:200], device="cpu")
    best = dict.fromkeys(cases, np.inf)
    order = list(cases)
    rng = np.random.default_rng(0)
    for _ in range(args.rounds):
        rng.shuffle(order)
        for name in order:
            start = time.perf_counter()
            fit_arrays(rois, windows=cases[name], device="cpu")
            best[name] = min(best[name], time.perf_counter() - start)
    table = markdown(pd.DataFrame(
        [{"ROIs": name, "fits per s": args.n / best[name]} for name in cases]
    ))  # fmt: skip
    notes = (
        f"{args.n} ROIs of {SIZE} x {SIZE} px, MLE, {args.threads} threads, best of "
        f"{args.rounds} interleaved rounds, on a loaded machine."
    )
    write_results("bench_fit_windows.md", "Windows in fit_arrays", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

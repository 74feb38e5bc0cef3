"""Benchmark: widefield accuracy against simulated truth, the iterated correction, apply's speed.

Runs :func:`latentz.validation.accuracy.widefield_study` (500 calibration particles over the 2048²
field,
320 independent test particles within ±2 µm; see its docstring) and reports, for each field
model, the RMSE after one global offset against three truths: the apparent position at best focus
(the paper's), the geometric position, and the geometric position after removing one affine map
of the field (what a magnification and rotation calibration absorbs), and the fraction of the
errors (against the paper's truth) within the 1σ that ``apply`` reported. Then the same with the
iterated z <-> lateral correction (Supp. Note 1), and the throughput of ``Calibration.apply`` on
2 x 10^5 spots over several rounds (median and range). Writes ``results/bench_widefield.md`` and
``results/bench_widefield.png``.

Run: ``python benchmarks/bench_widefield.py [--rounds 5] [--quick]`` (``--quick``: 120
calibration and 40 test particles, apply on 2 x 10^4 spots in 2 rounds, to check that it works;
writes the results with ``_quick`` in their names only).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _rounds import machine, spread, time_rounds, write_results

from latentz.calibration import calibrate_traces
from latentz.report.calibration_quality import coverage_table
from latentz.validation.accuracy import error_figure, rmse, score, widefield_study

OUT = Path(__file__).resolve().parent / "results"
Z_LIMIT_NM = 2000.0


def _affine_rmse(errors: pd.DataFrame) -> tuple[float, float]:
    """Lateral RMSE after removing one affine map of the field (6 parameters per axis)."""
    used = errors[errors["in_range"] & (np.abs(errors["true_z_nm"]) <= Z_LIMIT_NM)]
    design = np.column_stack([np.ones(len(used)), used["field_x"], used["field_y"]])
    out = []
    for axis in "xy":
        values = used[f"err_{axis}_nm"].to_numpy()
        resid = values - design @ np.linalg.lstsq(design, values, rcond=None)[0]
        out.append(float(np.sqrt(np.mean(resid**2))))
    return out[0], out[1]


def _rows(study: dict, label: str = "") -> list[dict]:
    rows = []
    for kind in study["errors"]:
        focus = rmse(study["errors"][kind], z_limit_nm=Z_LIMIT_NM)
        geo = rmse(study["geometric"][kind], z_limit_nm=Z_LIMIT_NM)
        ax, ay = _affine_rmse(study["geometric"][kind])
        errors = study["errors"][kind]
        used = errors[errors["in_range"] & (errors["true_z_nm"].abs() <= Z_LIMIT_NM)]
        cover = coverage_table(used, source="truth")["within 1σ (%)"]
        rows.append(
            {
                "model": kind + label,
                "x (focus)": focus["rmse_x_nm"],
                "y (focus)": focus["rmse_y_nm"],
                "z": focus["rmse_z_nm"],
                "x (geometric)": geo["rmse_x_nm"],
                "y (geometric)": geo["rmse_y_nm"],
                "x, y (geometric, affine removed)": f"{ax:.2f}, {ay:.2f}",
                "x, y uncorrected (focus)": f"{focus['raw_rmse_x_nm']:.1f}, "
                f"{focus['raw_rmse_y_nm']:.1f}",
                "1σ covers x / y / z (%)": " / ".join(f"{c:.1f}" for c in cover),
                "in range": focus["in_range"],
                "spots": int(focus["n"]),
            }
        )
    return rows


def _throughput(cal, spots: pd.DataFrame, n: int, rounds: int) -> np.ndarray:
    """Spots per second of ``cal.apply`` on ``n`` spots (the study's, repeated), warm, in each
    of ``rounds`` rounds."""
    big = spots.iloc[np.arange(n) % len(spots)].reset_index(drop=True)
    cal.apply(big.iloc[:1000])
    wall, _ = time_rounds(lambda: cal.apply(big), rounds)
    return n / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="rounds of the apply timing")
    parser.add_argument("--quick", action="store_true", help="a small study, 2 rounds")
    args = parser.parse_args()
    sizes = {"n_calibration": 120, "n_test": 40} if args.quick else {}
    n_apply = 20_000 if args.quick else 200_000
    if args.quick:
        args.rounds = 2
    started = machine()
    start = time.perf_counter()
    study = widefield_study(kinds=("zernike", "natural", "curves", "nearest", "auto"), **sizes)
    auto = study["calibrations"]["auto"].field_model
    for part in ("errors", "geometric"):
        study[part][f"auto ({auto})"] = study[part].pop("auto")
    elapsed = time.perf_counter() - start
    rows = _rows(study)
    zernike = study["calibrations"]["zernike"]
    iterated = calibrate_traces(
        zernike.traces,
        camera=zernike.camera,
        shape=zernike.shape,
        field_model="zernike",
        roi_size=zernike.options["roi_size"],
        field_shape=zernike.options["field_shape"],
        iterations=1,
    )
    errors, geometric = score(iterated, study)
    rows += _rows({"errors": {"zernike": errors}, "geometric": {"zernike": geometric}}, " +1 it.")
    table = pd.DataFrame(rows)
    rates = {
        kind: _throughput(cal, study["spots"], n_apply, args.rounds) / 1e3
        for kind, cal in study["calibrations"].items()
    }
    speed = pd.DataFrame(
        {
            "model": list(rates),
            f"apply, 10³ spots/s ({n_apply:.0e} spots), median (min–max)": [
                spread(r, 1) for r in rates.values()
            ],
            "rounds": args.rounds,
        }
    )
    print(table.round(2).to_string(index=False))
    print(speed.to_string(index=False))
    n_cal, n_test = sizes.get("n_calibration", 500), sizes.get("n_test", 320)
    figure = "bench_widefield_quick.png" if args.quick else "bench_widefield.png"
    OUT.mkdir(exist_ok=True)
    shown = study["errors"]["zernike"]
    fig = error_figure(
        shown[np.abs(shown["true_z_nm"]) <= Z_LIMIT_NM],
        title=f"Zernike widefield calibration: {n_test} independent particles, |z| <= 2 µm "
        "(truth: apparent position at best focus)",
    )
    fig.savefig(OUT / figure, dpi=110)
    notes = (
        f"{n_cal} calibration particles, {n_test} independent test particles; the study took "
        f"{elapsed:.0f} s. RMSE in nm after one global offset per axis, spots with |z| <= "
        f"{Z_LIMIT_NM:.0f} nm. 'focus': the apparent position at the particle's own best focus "
        "(the paper's definition of the true lateral position); 'geometric': where the "
        "particle is. Then the throughput of `Calibration.apply` in each round."
    )
    body = "\n\n".join(
        [
            table.round(2).to_markdown(index=False),
            speed.to_markdown(index=False),
            f"![errors against truth]({figure})",
        ]
    )
    write_results(
        "bench_widefield.md",
        "Widefield accuracy against simulated truth, and apply's speed",
        started,
        notes,
        body,
        quick=args.quick,
    )


if __name__ == "__main__":
    main()

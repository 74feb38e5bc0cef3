"""Benchmark: widefield accuracy against simulated truth, the iterated correction, apply's speed.

Runs :func:`latentz.accuracy.widefield_study` (500 calibration particles over the 2048² field,
320 independent test particles within ±2 µm; see its docstring) and reports, for each field
model, the RMSE after one global offset against three truths: the apparent position at best focus
(the paper's), the geometric position, and the geometric position after removing one affine map
of the field (what a magnification and rotation calibration absorbs). Then the same with the
iterated z <-> lateral correction (Supp. Note 1), and the throughput of ``Calibration.apply`` on
2 x 10^5 spots. Writes ``results/bench_widefield.md`` and ``results/bench_widefield.png``.

Run: ``python benchmarks/bench_widefield.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd

from latentz.accuracy import error_figure, rmse, score, widefield_study
from latentz.calibration import calibrate_traces

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
                "in range": focus["in_range"],
                "spots": int(focus["n"]),
            }
        )
    return rows


def _throughput(cal, spots: pd.DataFrame, n: int) -> float:
    """Spots per second of ``cal.apply`` on ``n`` spots (the study's, repeated), warm."""
    big = spots.iloc[np.arange(n) % len(spots)].reset_index(drop=True)
    cal.apply(big.iloc[:1000])
    start = time.perf_counter()
    cal.apply(big)
    return n / (time.perf_counter() - start)


def main() -> None:
    start = time.perf_counter()
    study = widefield_study(kinds=("zernike", "natural", "curves", "nearest", "auto"))
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
    speed = pd.DataFrame(
        {
            "model": list(study["calibrations"]),
            "apply, spots/s (2e5 spots)": [
                _throughput(cal, study["spots"], 200_000) for cal in study["calibrations"].values()
            ],
        }
    )
    print(table.round(2).to_string(index=False))
    print(speed.round(0).to_string(index=False))
    OUT.mkdir(exist_ok=True)
    shown = study["errors"]["zernike"]
    fig = error_figure(
        shown[np.abs(shown["true_z_nm"]) <= Z_LIMIT_NM],
        title="Zernike widefield calibration: 320 independent particles, |z| <= 2 µm "
        "(truth: apparent position at best focus)",
    )
    fig.savefig(OUT / "bench_widefield.png", dpi=110)
    text = [
        "# Widefield accuracy against simulated truth",
        "",
        "`python benchmarks/bench_widefield.py` (study and apply on this machine: "
        f"{elapsed:.0f} s for the study). RMSE in nm after one global offset per axis, spots "
        f"with |z| <= {Z_LIMIT_NM:.0f} nm. 'focus': the apparent position at the particle's own "
        "best focus (the paper's definition of the true lateral position); 'geometric': where "
        "the particle is.",
        "",
        table.round(2).to_markdown(index=False),
        "",
        speed.round(0).to_markdown(index=False),
        "",
        "![errors against truth](bench_widefield.png)",
        "",
    ]
    (OUT / "bench_widefield.md").write_text("\n".join(text))


if __name__ == "__main__":
    main()

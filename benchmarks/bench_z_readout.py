"""z from one shape value against the joint readout of wx, wy, ρ, on the same calibrations.

For each random family microscope (:mod:`latentz.validation.family`, seeds from ``--first``),
``calibrate`` with defaults, localize the test emitters once, then ``Calibration.apply`` them
with ``z_readout="shape"`` and with ``z_readout="joint"`` (:mod:`latentz.calibration.readout`)
and score both against the geometric truth (one offset and one plane per axis removed): the
share in range, z RMSE over each readout's own in-range spots and over the spots both keep, and
the share of in-range spots that their reported 1σ covers. Writes
``results/bench_z_readout.md``.

Run: ``python benchmarks/bench_z_readout.py --size ci --draws 16 --first 0``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.validation.study import calibrate_defaults, draw_microscope, family_data, localize_test
from latentz.validation.truth import score, summary

sys.path.insert(0, str(Path(__file__).parent))
from _draws import run_draws  # noqa: E402
from bench_validation_family import markdown  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_z_readout.md"
READOUTS = ("shape", "joint")


def compare(seed: int, size: str, renders: Path | None = None) -> dict:
    """One row: draw ``seed``'s calibration choices and both readouts' scores."""
    draw = draw_microscope(seed, size)
    data = family_data(draw, renders=renders)
    row = {"seed": seed, "astig nm": round(draw.astigmatism_nm), "form": draw.form}
    cal, choices = calibrate_defaults(data.stacks, data.z_nm, data.camera)
    row |= choices
    if cal is None:
        return row
    spots = localize_test(data, calibration=cal)
    scored = {r: score(data, cal.apply(spots, z_readout=r)) for r in READOUTS}
    both = np.logical_and.reduce([s["in_range"].to_numpy(bool) for s in scored.values()])
    for r, table in scored.items():
        scores = summary(table)
        common = table["err_z_nm"].to_numpy()[both]
        row |= {f"in range {r}": scores["in_range"], f"z RMSE {r}": scores["rmse_z"],
                f"z RMSE both {r}": float(np.sqrt(np.mean(common**2))) if both.any() else np.nan,
                f"cov z {r}": scores["cover_z"]}  # fmt: skip
    return row | {"spots both": int(both.sum()), "fails": ""}


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> None:
    table = pd.DataFrame(rows)
    done = table[table["fails"].fillna("") == ""]
    better = np.mean(done["z RMSE both joint"] <= done["z RMSE both shape"])
    lines = [
        "# z from one shape value against the joint readout, on the same calibrations",
        "",
        f"Command: `python benchmarks/bench_z_readout.py --draws {args.draws} --first "
        f"{args.first} --size {args.size}` ({len(rows)} draws done, {seconds / 60:.0f} min on a "
        "shared, loaded 2-core machine).",
        "",
        "z RMSE in nm after one offset and one plane per axis, over each readout's in-range "
        "spots and over the spots both keep (`spots both`); `cov z` is the share of in-range "
        "spots with |error| ≤ the reported 1σ.",
        "",
        markdown(table),
        "",
        f"The joint readout's z RMSE over the spots both keep is the smaller or equal on "
        f"{better:.0%} of the {len(done)} draws that calibrated; median z RMSE shape / joint: "
        f"{np.nanmedian(done['z RMSE shape']):.1f} / {np.nanmedian(done['z RMSE joint']):.1f} nm.",
        "",
    ]
    write_text_atomic(args.out, "\n".join(lines))


def main() -> None:
    run_draws(__doc__.splitlines()[0], compare, write, out=OUT, draws=16, first=0, size="ci")


if __name__ == "__main__":
    main()

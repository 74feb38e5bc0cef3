"""Benchmark: how far the calibration particles' lateral reference lies from their places.

Δx', Δy' are measured from each particle's position at its best focus z_f, which is where the
particle is taken to be (docs/method.md). With coma the fitted centre of an image moves through
focus, so that position lies off the particle's place by an amount that follows the coma across
the field; every Δ is measured from its own particle's reference, so the cross-validation that
gives the lateral field σ does not see it. For each family draw
(:func:`latentz.validation.family.draw_microscope`, calibrated with defaults): the kept
particles' position at z_f (their traces less their Δ) minus the place the simulation put them
(``calibration_truth``), RMS about a plane in (x, y) as the scoring removes one (``ref x``,
``ref y``, nm), and the part of σ that stands for it (``part x``, ``part y``, nm:
``Calibration.reference_sigma_nm``); beside them the test spots' lateral RMSE and 1σ coverage
after one plane (:func:`latentz.validation.truth.score`), the median reported σ and the median
of its field part (the held-out line at the spot's z and distance). Writes
``results/bench_lateral_reference.md``.

Run: ``python benchmarks/bench_lateral_reference.py [--draws 4] [--first 0] [--size ci]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.atomic import write_text_atomic
from latentz.validation.family import draw_microscope, family_data
from latentz.validation.study import calibrate_defaults
from latentz.validation.truth import localize_test, score, summary

sys.path.insert(0, str(Path(__file__).parent))
from _draws import run_draws  # noqa: E402
from bench_validation_family import markdown  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_lateral_reference.md"


def about_plane(values: np.ndarray, positions: np.ndarray) -> float:
    """RMS of ``values`` (n,) about their least-squares plane in ``positions`` (n, 2)."""
    design = np.column_stack([np.ones(len(values)), positions])
    residual = values - design @ np.linalg.lstsq(design, values, rcond=None)[0]
    return float(np.sqrt(np.mean(residual**2)))


def reference_offsets(cal, truth: pd.DataFrame) -> dict[str, float]:
    """RMS (nm) about a plane of the kept particles' position at z_f minus their true place
    (the nearest ``truth`` x, y within 2 px), per axis."""
    kept, px = cal.kept, cal.camera.pixel_size_nm
    distance, index = cKDTree(truth[["x", "y"]].to_numpy()).query(cal.positions[kept])
    out = {}
    for axis, delta in (("x", cal.local.dx), ("y", cal.local.dy)):
        at_focus = np.nanmedian(cal.traces[axis][kept] - delta[kept](cal.local.z_nm[kept]), axis=1)
        offset = (at_focus - truth[axis].to_numpy()[index]) * px
        use = np.isfinite(offset) & (distance <= 2.0)
        out[axis] = about_plane(offset[use], cal.positions[kept][use])
    return out


def coma(modes: dict[str, float]) -> int:
    """RMS of the two coma modes of ``modes`` (nm), rounded."""
    return round(float(np.hypot(modes["coma_x"], modes["coma_y"])))


def row_of(seed: int, size: str, renders: Path | None = None) -> dict:
    start = time.perf_counter()
    draw = draw_microscope(seed, size)
    row = {"seed": seed, "medium": draw.medium, "NA": round(draw.na, 2), "form": draw.form,
           "astig nm": round(draw.astigmatism_nm), "coma nm": coma(draw.mean_nm),
           "coma field nm": coma(draw.std_nm)}  # fmt: skip
    data = family_data(draw, renders=renders)
    cal, choices = calibrate_defaults(data.stacks, data.z_nm, data.camera)
    row |= choices
    if cal is None:
        return row
    ref = reference_offsets(cal, data.calibration_truth)
    located = cal.apply(localize_test(data, calibration=cal))
    errors = summary(score(data, located))
    used = located[located["in_range"].to_numpy(bool)]
    distance = cKDTree(cal.positions[cal.kept]).query(used[["x", "y"]].to_numpy())[0]
    z = used["z_nm"].to_numpy()
    row |= {"particles": int(cal.kept.size), "ref x": ref["x"], "ref y": ref["y"],
            "part x": cal.reference_sigma_nm("x"), "part y": cal.reference_sigma_nm("y"),
            "spots": int(errors["spots"]), "x RMSE": errors["rmse_x"],
            "y RMSE": errors["rmse_y"], "cov x": errors["cover_x"], "cov y": errors["cover_y"],
            "σ x": float(used["x_err_nm"].median()), "σ y": float(used["y_err_nm"].median()),
            "field σ x": float(np.nanmedian(cal._field_sigma("x", z, distance))),
            "field σ y": float(np.nanmedian(cal._field_sigma("y", z, distance))),
            "total s": round(time.perf_counter() - start)}  # fmt: skip
    return row


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> None:
    lines = [
        "# The particles' lateral reference against their places",
        "",
        f"Command: `python benchmarks/bench_lateral_reference.py --draws {args.draws} "
        f"--first {args.first} --size {args.size}` ({len(rows)} draws, {seconds / 60:.0f} min "
        "on a shared, loaded 2-core machine).",
        "",
        "`ref x`, `ref y`: the kept particles' position at z_f less their true place, RMS about "
        "a plane (nm); `part x`, `part y`: the part of σ that stands for it (nm); RMSE and "
        "`cov` (share of |error| ≤ 1σ) of the test spots after one plane "
        "per axis; `σ`, `field σ`: medians over the spots of the reported σ and its field part "
        "(nm). Coma: RMS of the mean coma and of its variation over the field (nm).",
        "",
        markdown(pd.DataFrame(rows)),
        "",
    ]
    write_text_atomic(args.out, "\n".join(lines))


def main() -> None:
    run_draws(__doc__.splitlines()[0], row_of, write, out=OUT, draws=4, first=0, size="ci")


if __name__ == "__main__":
    main()

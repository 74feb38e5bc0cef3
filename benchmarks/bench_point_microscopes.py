"""Benchmark: defaults on point-particle microscopes laid out as the held-out test microscopes.

Each microscope is ``latentz.validation.make_data("full", ...)``: NA 0.55 in air, 640 nm, 130 nm
pixels, 256 × 256 px; 128 point emitters in two stacks through ±3 µm in 50 nm steps at 2·10⁵
photons; 600 test spots of 60 other point emitters within ±2 µm at 2·10⁴–2·10⁵ photons. The
aberration fields are smooth random fields with a local defect (``random``) or low-order
polynomials of field position (``polynomial``), one seed each. Each is calibrated with
``calibrate(stacks, z, camera=camera)`` and nothing else, its test frames localized with
``localize(calibration=cal)`` and ``cal.apply``, and scored against geometry
(:func:`latentz.validation.truth.score`: one offset and one plane per axis removed).

One row per microscope: the choices, z and x / y RMSE (nm), the share of spots within their
reported 1σ (``cov``), the same without the particles' own lateral reference
(``apply(lateral_reference="focus")``, ``cov x focus``), that part of σ (``ref x``), and the kept
particles' positions at best focus less their true places, RMS about a plane (``off x``, nm).
Writes ``results/bench_point_microscopes.md`` after every microscope (atomically).

With ``--rois 11,15,…`` each microscope is instead calibrated at each of those ROIs (every other
option at its default), and one row per microscope and ROI gives the kept particles' offsets
from their places at best focus (RMS about a plane), their part shared by neighbours, and the
particles' own reference part of σ: ``results/bench_point_microscopes_rois.md``.

Run: ``python benchmarks/bench_point_microscopes.py [--seeds 0,1,2] [--fields random,polynomial]
[--rois 11,15,19,23,27,31]`` (about two minutes per microscope on a 2-core machine).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.calibration import calibrate
from latentz.validation import AberrationFields, ValidationData, make_data
from latentz.validation.truth import localize_test, score, summary

sys.path.insert(0, str(Path(__file__).parent))
from bench_lateral_reference import (  # noqa: E402
    plane_residual,
    reference_offsets,
    rms,
    smooth_rms,
)

OUT = Path(__file__).resolve().parent / "results" / "bench_point_microscopes.md"
FIELDS = ("random", "polynomial")


def point_data(form: str, seed: int) -> ValidationData:
    """The microscope of ``form`` (one of :data:`FIELDS`) and ``seed``, with its stacks and test
    frames (module notes)."""
    fields = None
    if form == "polynomial":
        fields = AberrationFields.polynomial((256, 256), seed=seed, pixel_size_nm=130.0)
    return make_data("full", seed=seed, bead_nm=0.0, test_photons=(2e4, 2e5), fields=fields)


def row_of(form: str, seed: int) -> dict:
    """One microscope's row (module notes)."""
    start = time.perf_counter()
    data = point_data(form, seed)
    cal = calibrate(data.stacks, data.z_nm, camera=data.camera)
    spots = localize_test(data, calibration=cal)
    row = {"fields": form, "seed": seed, "ROI": cal.roi_size, "shape": cal.shape,
           "field model": cal.field_model, "kept": cal.kept.size}  # fmt: skip
    scored = summary(score(data, cal.apply(spots)))
    focus = summary(score(data, cal.apply(spots, lateral_reference="focus")))
    row |= {"spots": scored["spots"], "in range": scored["in_range"]}
    row |= {f"{a} RMSE": scored[f"rmse_{a}"] for a in "xyz"}
    row |= {f"cov {a}": scored[f"cover_{a}"] for a in "xyz"}
    offsets = reference_offsets(cal, data.calibration_truth)
    for a in "xy":
        row[f"cov {a} focus"] = focus[f"cover_{a}"]
        row[f"ref {a}"] = cal.reference_sigma_nm(a)
        row[f"off {a}"] = rms(plane_residual(offsets[a], cal.positions[cal.kept]))
    return row | {"total s": round(time.perf_counter() - start)}


def reference_rows(form: str, seed: int, rois: list[int]) -> list[dict]:
    """One row per ROI of ``rois`` for one microscope calibrated at that ROI (every other option
    at its default): the kept particles' positions at best focus less their places, RMS about a
    plane (``off``, nm), the part of that shared by nearest neighbours (``shared``, nm), and the
    particles' own reference part of σ (``ref``, nm)."""
    data = point_data(form, seed)
    rows = []
    for roi in rois:
        cal = calibrate(data.stacks, data.z_nm, camera=data.camera, roi_size=roi)
        offsets = reference_offsets(cal, data.calibration_truth)
        places = cal.positions[cal.kept]
        row = {"fields": form, "seed": seed, "ROI": roi, "kept": cal.kept.size}
        for a in "xy":
            residual = plane_residual(offsets[a], places)
            row |= {f"off {a}": rms(residual), f"shared {a}": smooth_rms(residual, places),
                    f"ref {a}": cal.reference_sigma_nm(a)}  # fmt: skip
        rows.append(row)
    return rows


def write_reference(rows: list[dict], command: str, seconds: float) -> None:
    """The table of :func:`reference_rows` so far."""
    text = "\n".join([
        "# The particles' reference offsets against the ROI, on point-particle microscopes",
        "",
        f"Command: `{command}` ({seconds / 60:.0f} min on a 2-core machine). Each microscope "
        "calibrated at each ROI, every other option at its default. `off x`: the kept "
        "particles' positions at best focus less their places, RMS about a plane (nm); "
        "`shared x`: its part shared by nearest neighbours (nm); `ref x`: the particles' own "
        "reference part of σ (nm).",
        "",
        pd.DataFrame(rows).to_markdown(index=False, floatfmt=".3g"),
        "",
    ])  # fmt: skip
    write_text_atomic(OUT.with_name("bench_point_microscopes_rois.md"), text)


def write(rows: list[dict], command: str, seconds: float) -> None:
    table = pd.DataFrame(rows)
    pooled = {a: np.average(table[f"cov {a}"], weights=table["spots"]) for a in "xyz"}
    text = "\n".join([
        "# Defaults on point-particle microscopes laid out as the held-out ones",
        "",
        f"Command: `{command}` ({len(rows)} microscopes, {seconds / 60:.0f} min on a 2-core "
        "machine). NA 0.55 in air, 640 nm, 130 nm pixels; 128 point particles through ±3 µm in "
        "50 nm steps at 2·10⁵ photons; 600 spots of 60 point emitters within ±2 µm at "
        "2·10⁴–2·10⁵ photons. RMSE in nm after one offset and one plane per axis; `cov`: share "
        "of in-range spots within 1σ; `cov x focus`: without the particles' own lateral "
        "reference, `ref x` (nm); `off x`: the kept particles' positions at best focus less "
        "their places, RMS about a plane (nm).",
        "",
        table.to_markdown(index=False, floatfmt=".3g"),
        "",
        "Pooled (weighted by spots): 1σ covers x / y / z "
        + " / ".join(f"{pooled[a]:.1%}" for a in "xyz") + ".",
        "",
    ])  # fmt: skip
    write_text_atomic(OUT, text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--fields", default=",".join(FIELDS), help="random and/or polynomial")
    parser.add_argument("--rois", default="", help="comma-separated ROIs (px): the reference "
                        "offsets at each instead (results/bench_point_microscopes_rois.md)")
    args = parser.parse_args()
    forms = args.fields.split(",")
    if not set(forms) <= set(FIELDS):
        parser.error(f"--fields: each of {FIELDS}, got {args.fields!r}")
    seeds = [int(s) for s in args.seeds.split(",")]
    command = "python benchmarks/bench_point_microscopes.py " + " ".join(sys.argv[1:])
    warnings.simplefilter("ignore")
    rois = [int(r) for r in args.rois.split(",") if r]
    start, rows = time.perf_counter(), []
    for form in forms:
        for seed in seeds:
            if rois:
                rows += reference_rows(form, seed, rois)
                write_reference(rows, command.strip(), time.perf_counter() - start)
            else:
                rows.append(row_of(form, seed))
                write(rows, command.strip(), time.perf_counter() - start)
            print(rows[-1], flush=True)


if __name__ == "__main__":
    main()

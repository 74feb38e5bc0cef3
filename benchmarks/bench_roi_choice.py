"""Benchmark: the automatic ROI against brute force on independent microscopes.

Two sets of microscopes, neither made by latentz's own simulator:

- ``independent``: draws of the independent validation microscope (:mod:`latentz.validation`:
  other optics code, smooth random aberration fields with a local defect; NA, pixel size and
  astigmatism varied per draw, :data:`DRAWS`), test emitters of 10³–10⁴ photons;
- ``point``: the point-particle microscopes laid out as the held-out test microscopes
  (``benchmarks/bench_point_microscopes.py``: NA 0.55 in air, 640 nm, 130 nm pixels, 256² px,
  128 point particles through ±3 µm, 600 spots of 2·10⁴–2·10⁵ photons within ±2 µm), with
  smooth random fields and a local defect (draws 0, 1, …) or polynomial fields (seeds the same
  numbers, after the random ones).

``calibrate`` runs with defaults only, then once at every ROI of ``--rois`` (default: every
candidate that the default considered, ``cal.options["roi_choice"]``), and each calibration
localizes the same test frames. Each is scored against geometric truth: the emitter's defocus
from the focal surface plus that surface's height at its place (where the optics put it; no
latentz function), after one global offset and one plane per axis (:func:`latentz.validation.
truth.score`, the plane fitted without gross errors). One row per microscope and ROI: the
shape and field model chosen there, z, x and y RMSE over the spots in range, the share of test
spots localized in range, and the 1σ coverage of ``x_err_nm``, ``y_err_nm`` and
``z_err_nm``; the row the default chose is marked, and the brute-force best is the one with the
smallest z RMSE.

Run: ``python benchmarks/bench_roi_choice.py [--microscopes independent] [--size small]
[--draws 2] [--rois 11,15,19,23,27] [--out FILE]``; writes ``results/bench_roi_choice.md``
(``--microscopes point``: ``results/bench_roi_choice_point.md``) after every microscope,
atomically. Timings are of a 2-core machine.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.calibration import calibrate
from latentz.camera import Camera
from latentz.validation import Microscope, ValidationData, make_data
from latentz.validation.fields import AberrationFields
from latentz.validation.truth import localize_test, score, summary

sys.path.insert(0, str(Path(__file__).parent))
from bench_point_microscopes import FIELDS, point_data  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"
#: (NA, pixel size nm, scale of the random aberration fields) of each independent draw, in order.
DRAWS = ((0.55, 130.0, 1.0), (0.8, 100.0, 1.5), (0.45, 160.0, 0.7), (0.7, 110.0, 1.0))


def draw(k: int, size: str) -> tuple[dict, ValidationData]:
    """The k-th independent validation microscope of :data:`DRAWS`: its settings and data."""
    na, pixel, scale = DRAWS[k % len(DRAWS)]
    microscope = Microscope(na=na, pixel_size_nm=pixel)
    n = {"small": 128, "full": 256}[size]
    fields = AberrationFields.random((n, n), seed=k, pixel_size_nm=pixel, scale=scale)
    camera = Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=pixel)
    data = make_data(size, seed=k, microscope=microscope, fields=fields, camera=camera)
    return {"draw": k, "NA": na, "pixel_nm": pixel, "field_scale": scale}, data


def point_draw(k: int, draws: int) -> tuple[dict, ValidationData]:
    """The k-th point-particle microscope of ``draws``: random fields for seeds 0, 1, … (the
    first half, rounded up), then polynomial fields for seeds 0, 1, …"""
    half = (draws + 1) // 2
    form, seed = FIELDS[k // half], k % half
    return {"draw": k, "fields": form, "seed": seed}, point_data(form, seed)


def score_roi(data: ValidationData, roi: int | None) -> tuple[dict, object]:
    """Calibrate with ``roi`` (None: the default) and score the test frames."""
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(data.stacks, data.z_nm, camera=data.camera, roi_size=roi)
        errors = summary(score(data, cal.apply(localize_test(data, calibration=cal))))
    row = {"roi": cal.roi_size, "shape": cal.shape, "field": cal.field_model}
    row |= {f"{a}_rmse_nm": errors[f"rmse_{a}"] for a in "zxy"}
    row["found"] = errors["spots"] / len(data.test_truth)
    row |= {f"cover_{a}": errors[f"cover_{a}"] for a in "xyz"}
    return row | {"s": time.perf_counter() - start}, cal


def rows_of(settings: dict, data: ValidationData, rois: list[int] | None) -> list[dict]:
    """One row per ROI of ``rois`` (None: the candidates the default considered) for one
    microscope, with the default's choice marked and each z RMSE over the best's."""
    default, cal = score_roi(data, None)
    candidates = rois or sorted(int(r) for r in cal.options["roi_choice"]["candidates"])
    found = {default["roi"]: default}
    for roi in candidates:
        if roi not in found:
            found[roi] = score_roi(data, roi)[0]
    best = min(found.values(), key=lambda r: r["z_rmse_nm"])
    return [settings | found[roi] | {"chosen": roi == default["roi"],
                                     "ratio_to_best": found[roi]["z_rmse_nm"] / best["z_rmse_nm"]}
            for roi in sorted(found)]  # fmt: skip


def write(rows: list[dict], out: Path, command: str, seconds: float) -> None:
    """The table so far, with each microscope's chosen ROI against its brute-force best."""
    table = pd.DataFrame(rows)
    ratios = ", ".join(f"{v:.2f}" for v in table.loc[table["chosen"], "ratio_to_best"])
    text = (
        f"# Automatic ROI against brute force\n\nCommand: `{command}` "
        f"({table['draw'].nunique()} microscopes, {seconds / 60:.0f} min on a 2-core machine). "
        "RMSE in nm over the spots in range after one offset and one plane per axis; `found`: "
        "the share of test spots localized in range; `cover`: the share of them within 1σ.\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
        + f"\n\nChosen ROI's z RMSE / brute-force best, per microscope: {ratios}.\n"
    )
    write_text_atomic(out, text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--microscopes", default="independent", choices=("independent", "point"))
    parser.add_argument("--size", default="small", choices=("small", "full"),
                        help="independent microscopes only; point microscopes are full size")
    parser.add_argument("--draws", type=int, default=2)
    parser.add_argument("--rois", default="", help="comma-separated ROI sizes (px)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    rois = [int(r) for r in args.rois.split(",") if r] or None
    name = "bench_roi_choice" + ("_point" if args.microscopes == "point" else "")
    out = args.out or OUT / f"{name}.md"
    command = "python benchmarks/bench_roi_choice.py " + " ".join(sys.argv[1:])
    start, rows = time.perf_counter(), []
    for k in range(args.draws):
        settings, data = (point_draw(k, args.draws) if args.microscopes == "point"
                          else draw(k, args.size))  # fmt: skip
        done = rows_of(settings, data, rois)
        rows += done
        print(pd.DataFrame(done).to_string(), flush=True)
        write(rows, out, command.strip(), time.perf_counter() - start)


if __name__ == "__main__":
    main()

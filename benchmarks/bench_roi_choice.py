"""Benchmark: the automatic ROI against brute force on independent microscopes.

For each draw of the independent validation microscope (:mod:`latentz.validation`: other optics
code, smooth random aberration fields with a local defect; NA, pixel size and astigmatism
varied per draw), ``calibrate`` runs with defaults only, then once at every candidate ROI it
considered (``cal.options["roi_choice"]``), and each calibration localizes the same test frames
(point emitters of 10³–10⁴ photons). Each is scored against geometric truth: the emitter's
defocus from the focal surface plus that surface's height at its place (where the optics put
it; no latentz function), after one global offset and one plane (:func:`latentz.validation.
truth.score`, the plane fitted without gross errors). One row per draw and ROI:
z RMSE, the share of test spots localized, and 1σ coverage of ``z_err_nm``; the row the
default chose is marked, and the brute-force best is the one with the smallest z RMSE.

Run: ``python benchmarks/bench_roi_choice.py [--size small] [--draws 3]``; writes
``results/bench_roi_choice.md``. Timings are of a shared, loaded machine.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import pandas as pd

from latentz.calibration import calibrate
from latentz.camera import Camera
from latentz.validation import Microscope, make_data
from latentz.validation.fields import AberrationFields
from latentz.validation.truth import localize_test, score, summary

OUT = Path(__file__).resolve().parent / "results"
#: (NA, pixel size nm, scale of the random aberration fields) of each draw, in order.
DRAWS = ((0.55, 130.0, 1.0), (0.8, 100.0, 1.5), (0.45, 160.0, 0.7), (0.7, 110.0, 1.0))


def draw(k: int, size: str):
    """The k-th validation microscope of :data:`DRAWS` and its data."""
    na, pixel, scale = DRAWS[k % len(DRAWS)]
    microscope = Microscope(na=na, pixel_size_nm=pixel)
    n = {"small": 128, "full": 256}[size]
    fields = AberrationFields.random((n, n), seed=k, pixel_size_nm=pixel, scale=scale)
    camera = Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=pixel)
    return (na, pixel, scale), make_data(size, seed=k, microscope=microscope, fields=fields,
                                         camera=camera)  # fmt: skip


def score_roi(data, roi: int | None) -> tuple[dict, object]:
    """Calibrate with ``roi`` (None: the default) and score the test frames."""
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(data.stacks, data.z_nm, camera=data.camera, roi_size=roi)
        errors = summary(score(data, localize_test(data, calibration=cal)))
    row = {
        "roi": cal.roi_size,
        "shape": cal.shape,
        "field": cal.field_model,
        "z_rmse_nm": errors["rmse_z"],
        "found": errors["spots"] / len(data.test_truth),
        "cover_z": errors["cover_z"],
        "s": time.perf_counter() - start,
    }
    return row, cal


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small", choices=("small", "full"))
    parser.add_argument("--draws", type=int, default=3)
    args = parser.parse_args()
    rows = []
    for k in range(args.draws):
        optics, data = draw(k, args.size)
        default, cal = score_roi(data, None)
        candidates = sorted(int(r) for r in cal.options["roi_choice"]["candidates"])
        found = {default["roi"]: default}
        for roi in candidates:
            if roi not in found:
                found[roi] = score_roi(data, roi)[0]
        best = min(found.values(), key=lambda r: r["z_rmse_nm"])
        for roi in candidates:
            row = found[roi]
            rows.append({"draw": k, "NA": optics[0], "pixel_nm": optics[1],
                         "field_scale": optics[2], **row, "chosen": roi == default["roi"],
                         "ratio_to_best": row["z_rmse_nm"] / best["z_rmse_nm"]})  # fmt: skip
            print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    OUT.mkdir(exist_ok=True)
    ratios = ", ".join(f"{v:.2f}" for v in table.loc[table["chosen"], "ratio_to_best"])
    text = (
        f"# Automatic ROI against brute force ({args.size}, {args.draws} draws)\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
        + f"\n\nChosen ROI's z RMSE / brute-force best, per draw: {ratios}.\n"
    )
    (OUT / "bench_roi_choice.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()

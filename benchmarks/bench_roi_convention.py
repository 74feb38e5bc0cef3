"""Benchmark: how much z and its coverage depend on where each test spot's ROI sits.

Calibration follows each particle through focus in one fixed ROI, centred on the particle's
place (:mod:`latentz.calibration.traces`); ``localize`` centres each spot's ROI on its own
fitted centre (:mod:`latentz.localization.recentre`). Out of focus the fitted centre moves from
the emitter's place by the lateral shift Δx'(z), Δy'(z) that the calibration measures (coma:
up to pixels at the ends of the range), so a spot's ROI can sit a pixel or more from where the
calibration's would, and a spot that fills its ROI is then fitted narrower or wider than the
calibration's images of the same z.

Per family draw (defaults only, :func:`latentz.validation.study.calibrate_defaults`), the test
frames are localized with ``localize(calibration=cal)``; every spot whose ROI pixel differs
from the calibration's (its fitted centre less its lateral shift, rounded) is fitted again in
the ROI on that pixel (one step, maximum likelihood with sandwich errors as ``localize`` fits;
spots whose ROI would leave the frame keep their fit); so, apart, are only those whose lateral
shift exceeds half a pixel on an axis (there the ROI cannot sit on the calibration's pixel;
below it both pixels lie within a pixel of the spot's place). Each table goes through
``cal.apply`` and is scored against geometry (:func:`latentz.validation.truth.score`). Where
the two conventions agree, the rows agree.

Writes ``results/bench_roi_convention.md`` after every draw (atomically).

Run: ``python benchmarks/bench_roi_convention.py [--first 0] [--draws 4] [--size ci]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.fit import fit_rois
from latentz.validation.family import draw_microscope, family_data
from latentz.validation.study import calibrate_defaults
from latentz.validation.truth import localize_test, score, summary

sys.path.insert(0, str(Path(__file__).parent))
from _draws import run_draws  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_roi_convention.md"


def calibration_pixels(cal, located: pd.DataFrame, least_px: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(col, row) of the ROI centre calibration's convention gives each spot: its fitted centre
    less the lateral shift that ``apply`` took off (px), rounded, where that shift exceeds
    ``least_px`` on either axis; the spot's own pixel elsewhere and where it is out of range."""
    px = cal.camera.pixel_size_nm
    x, y = located["x"].to_numpy(float), located["y"].to_numpy(float)
    place_x, place_y = located["x_nm"].to_numpy(float) / px, located["y_nm"].to_numpy(float) / px
    with np.errstate(invalid="ignore"):
        far = np.maximum(np.abs(x - place_x), np.abs(y - place_y)) > least_px
    use = located["in_range"].to_numpy(bool) & far
    cols, rows = np.where(use, place_x, x), np.where(use, place_y, y)
    return np.rint(cols).astype(int), np.rint(rows).astype(int)


def refit_at(data, spots: pd.DataFrame, cols: np.ndarray, rows: np.ndarray,
             roi_size: int) -> tuple[pd.DataFrame, np.ndarray]:  # fmt: skip
    """``spots`` fitted again in the ROIs centred on (``cols``, ``rows``) where that differs
    from their own pixel and the ROI lies inside the frame; and which were."""
    half = roi_size // 2
    h, w = data.frames.shape[1:]
    moved = (cols != np.rint(spots["x"]).astype(int)) | (rows != np.rint(spots["y"]).astype(int))
    moved &= (cols >= half) & (rows >= half) & (cols < w - half) & (rows < h - half)
    out = spots.copy()
    if not moved.any():
        return out, moved
    where = zip(spots["frame"].to_numpy(int)[moved], cols[moved], rows[moved], strict=True)
    rois = np.stack([data.frames[f, r - half : r + half + 1, c - half : c + half + 1]
                     for f, c, r in where])  # fmt: skip
    fit = fit_rois(rois, camera=data.camera, errors="sandwich")
    fit["x"] += cols[moved] - half
    fit["y"] += rows[moved] - half
    index = out.index[moved]
    for column in fit.columns.intersection(out.columns):
        out.loc[index, column] = fit[column].to_numpy()
    return out, moved


def row_of(seed: int, size: str) -> dict:
    """One draw: its settings, what calibrate chose, and z / x / y RMSE and 1σ coverage of the
    spots as localized, refitted on the calibration's ROI pixel, and refitted there only where
    the spot's lateral shift exceeds half a pixel."""
    draw = draw_microscope(seed, size)
    row = {"seed": seed, "medium": draw.medium, "NA": round(draw.na, 2),
           "px nm": round(draw.pixel_size_nm), "form": draw.form,
           "astig nm": round(draw.astigmatism_nm)}  # fmt: skip
    data = family_data(draw)
    cal, choices = calibrate_defaults(data.stacks, data.z_nm, data.camera)
    row |= choices
    if cal is None:
        return row
    spots = localize_test(data, calibration=cal).drop_duplicates(["emitter", "frame"])
    located = cal.apply(spots)
    tables = {"": located}
    for name, least in ((" refit", 0.0), (" half", 0.5)):
        refitted, moved = refit_at(data, spots, *calibration_pixels(cal, located, least),
                                   cal.roi_size)  # fmt: skip
        row[f"moved{name}"] = int(moved.sum())
        tables[name] = cal.apply(refitted)
    for name, table in tables.items():
        got = summary(score(data, table))
        row |= {f"spots{name}": int(got["spots"]),
                **{f"{a} RMSE{name}": got[f"rmse_{a}"] for a in "zxy"},
                **{f"cov {a}{name}": got[f"cover_{a}"] for a in "xyz"}}  # fmt: skip
    return row | {"fails": ""}


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> None:
    table = pd.DataFrame(rows)

    def cell(value) -> str:
        if isinstance(value, float):
            return "" if np.isnan(value) else f"{value:.3g}"
        return str(value)

    lines = [
        "# Where each test spot's ROI sits: as localized, and on the calibration's pixel",
        "",
        f"Command: `python benchmarks/bench_roi_convention.py --first {args.first} --draws "
        f"{args.draws} --size {args.size}` ({len(rows)} draws, {seconds / 60:.0f} min on a "
        "shared, loaded 2-core machine).",
        "",
        "`moved`: spots refitted on another pixel; RMSE in nm, `cov`: share of in-range spots "
        "with |error| ≤ the reported 1σ; ` refit`: after the refit of every spot whose ROI "
        "pixel differs; ` half`: of those whose lateral shift also exceeds half a pixel.",
        "",
        "| " + " | ".join(table.columns) + " |",
        "|" + "---|" * len(table.columns),
        *("| " + " | ".join(cell(v) for v in r) + " |" for r in table.itertuples(False)),
        "",
    ]
    write_text_atomic(args.out, "\n".join(lines))


def main() -> None:
    run_draws(__doc__.splitlines()[0], row_of, write, out=OUT, draws=4, first=0, size="ci")


if __name__ == "__main__":
    main()

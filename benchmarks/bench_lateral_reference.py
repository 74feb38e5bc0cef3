"""Benchmark: how far the calibration particles' lateral reference lies from their places.

Δx', Δy' are measured from each particle's position at its best focus z_f, which is where the
particle is taken to be (docs/method.md). With coma the fitted centre of an image moves through
focus, so that position lies off the particle's place by an amount that follows the coma across
the field; every Δ is measured from its own particle's reference, so the cross-validation that
gives the lateral field σ does not see it. For each family draw
(:func:`latentz.validation.family.draw_microscope`, calibrated with defaults), or for a saved
study (``--study FILE``, a pickled :class:`~latentz.validation.ValidationData` such as
``bench_widefield_independent.py --cache`` keeps): the kept particles' position at z_f (their
traces less their Δ) minus the place the simulation put them (``calibration_truth``), RMS about
a plane in (x, y) as the scoring removes one (``ref x``, ``ref y``, nm), and its part shared by
neighbouring particles, the one an emitter between them inherits (``smooth x``, ``smooth y``:
the square root of the mean product of each particle's value with its nearest neighbour's;
per-particle scatter the cross-validation already holds); the part of σ that stands for it
(``part x``, ``part y``, nm: ``Calibration.reference_sigma_nm``); beside them the test spots'
lateral RMSE and 1σ coverage after one plane (:func:`latentz.validation.truth.score`) with and
without that part (``cov x``, ``cov x focus``), the part that would make 1σ cover 68.27 %
(``need x``, ``need y``, nm), the median reported σ and the median of its field part (the
held-out line at the spot's z and distance). ``cen r x``, ``cen r y``: the correlation, both
about a plane, of the references' offsets with the bead's fitted centre less its intensity
centroid (background removed, in the calibration's ROI), averaged over the planes within the
depth of focus; +1 if the centroid lay at the place, and ``cen k x``, ``cen k y`` the
least-squares factor from the one to the other (1 if so). Writes
``results/bench_lateral_reference.md``.

Run: ``python benchmarks/bench_lateral_reference.py [--draws 4] [--first 0] [--size ci]
[--renders DIR]`` or ``python benchmarks/bench_lateral_reference.py --study FILE``.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from latentz._shared.atomic import write_text_atomic
from latentz.calibration.errors import DEPTH_FRACTION, ONE_SIGMA
from latentz.calibration.field_errors import field_sigma
from latentz.calibration.local import focus_depth_nm
from latentz.validation.family import draw_microscope, family_data
from latentz.validation.study import calibrate_defaults
from latentz.validation.truth import localize_test, score, summary

sys.path.insert(0, str(Path(__file__).parent))
from _draws import run_draws  # noqa: E402
from bench_validation_family import markdown  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_lateral_reference.md"


def plane_residual(values: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """``values`` (n,) less their least-squares plane in ``positions`` (n, 2), over the finite
    values (NaN elsewhere)."""
    use = np.isfinite(values)
    design = np.column_stack([np.ones(len(values)), positions])
    return values - design @ np.linalg.lstsq(design[use], values[use], rcond=None)[0]


def rms(values: np.ndarray) -> float:
    """Root mean square of the finite ``values``."""
    return float(np.sqrt(np.nanmean(values**2)))


def smooth_rms(residual: np.ndarray, positions: np.ndarray) -> float:
    """The part of ``residual`` (n,) shared by neighbours: the square root of the mean product of
    each finite value with its nearest finite neighbour's in ``positions`` (n, 2), or 0."""
    use = np.isfinite(residual)
    values, points = residual[use], positions[use]
    neighbour = cKDTree(points).query(points, k=2)[1][:, 1]
    return float(np.sqrt(max(np.mean(values * values[neighbour]), 0.0)))


def reference_offsets(cal, truth: pd.DataFrame) -> dict[str, np.ndarray]:
    """Per kept particle and axis (n,), nm: its position at z_f (the median over its planes within
    its span of its trace less its Δ) minus its true place (the nearest ``truth`` x, y within
    2 px; NaN where none is)."""
    kept, px = cal.kept, cal.camera.pixel_size_nm
    distance, index = cKDTree(truth[["x", "y"]].to_numpy()).query(cal.positions[kept])
    z, span = cal.local.z_nm[kept], cal.z_span_nm[kept]
    inside = (z >= span[:, :1]) & (z <= span[:, 1:])
    out = {}
    for axis, delta in (("x", cal.local.dx), ("y", cal.local.dy)):
        moved = cal.traces[axis][kept] - delta[kept](np.where(inside, z, 0.0))
        at_focus = np.nanmedian(np.where(inside, moved, np.nan), axis=1)
        out[axis] = np.where(distance <= 2.0, (at_focus - truth[axis].to_numpy()[index]) * px,
                             np.nan)  # fmt: skip
    return out


def fit_less_centroid(cal, stacks: list[np.ndarray]) -> dict[str, np.ndarray]:
    """Per kept particle and axis (n,), nm: its fitted centre less its intensity centroid, the
    mean over its planes within the depth of focus about z_f (:func:`~latentz.calibration.local.
    focus_depth_nm` at ``errors.DEPTH_FRACTION``). The centroid is taken in the calibration's
    ROI about the fitted centre, less the median of the ROI's border."""
    kept, half = cal.kept, cal.roi_size // 2
    z = cal.local.z_nm[kept]
    depth = focus_depth_nm(z, cal.traces["amplitude"][kept], DEPTH_FRACTION)
    near = np.abs(z - cal.local.z_f[kept][:, None]) <= depth[:, None]
    grid = np.arange(-half, half + 1)
    out = {axis: np.full(kept.size, np.nan) for axis in "xy"}
    for i, p in enumerate(kept):
        stack = stacks[cal.traces.stack[p]]
        offset = cal.traces.offset_px[p]
        planes = np.flatnonzero(near[i] & np.isfinite(cal.traces["x"][p]))
        gaps = {"x": [], "y": []}
        for k in planes:
            fit = np.array([cal.traces["x"][p, k], cal.traces["y"][p, k]])
            col, row = np.rint(fit - offset).astype(int)
            if min(row, col) < half or max(row, col) + half >= min(stack.shape[1:]):
                continue
            window = stack[k, row - half : row + half + 1, col - half : col + half + 1].astype(
                float
            )
            border = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
            light = window - np.median(border)
            total = light.sum()
            centroid = (np.array([light.sum(axis=0) @ grid, light.sum(axis=1) @ grid]) / total
                        + [col, row] + offset)  # fmt: skip
            for j, axis in enumerate("xy"):
                gaps[axis].append(fit[j] - centroid[j])
        for axis in "xy":
            if gaps[axis]:
                out[axis][i] = np.mean(gaps[axis]) * cal.camera.pixel_size_nm
    return out


def needed_part(errors: pd.DataFrame, axis: str) -> float:
    """The σ (nm) that, added in quadrature to each in-range spot's reported σ on ``axis``,
    makes 1σ cover 68.27 % of their |error| (0 if it covers that already)."""
    used = errors[errors["in_range"].to_numpy(bool)]
    error, sigma = np.abs(used[f"err_{axis}_nm"].to_numpy()), used[f"{axis}_err_nm"].to_numpy()

    def short(part: float) -> float:
        return float(np.mean(error <= np.hypot(sigma, part))) - ONE_SIGMA

    return 0.0 if short(0.0) >= 0 else float(brentq(short, 0.0, float(error.max())))


def coma(modes: dict[str, float]) -> int:
    """RMS of the two coma modes of ``modes`` (nm), rounded."""
    return round(float(np.hypot(modes["coma_x"], modes["coma_y"])))


def study_row(data, cal) -> dict:
    """The columns of one calibrated study (module notes)."""
    positions = cal.positions[cal.kept]
    ref = reference_offsets(cal, data.calibration_truth)
    cen = fit_less_centroid(cal, data.stacks)
    spots = localize_test(data, calibration=cal)
    located = cal.apply(spots)
    errors = score(data, located)
    focus = score(data, cal.apply(spots, lateral_reference="focus"))
    used = located[located["in_range"].to_numpy(bool)]
    distance = cKDTree(positions).query(used[["x", "y"]].to_numpy())[0]
    z = used["z_nm"].to_numpy()
    scored, unscored = summary(errors), summary(focus)
    row = {"particles": int(cal.kept.size), "spots": int(scored["spots"])}
    for axis in "xy":
        offset = plane_residual(ref[axis], positions)
        seen = plane_residual(cen[axis], positions)
        both = np.isfinite(offset) & np.isfinite(seen)
        row |= {f"ref {axis}": rms(offset), f"smooth {axis}": smooth_rms(offset, positions),
                f"part {axis}": cal.reference_sigma_nm(axis),
                f"cen r {axis}": float(np.corrcoef(offset[both], seen[both])[0, 1]),
                f"cen k {axis}": float(seen[both] @ offset[both] / (seen[both] @ seen[both])),
                f"{axis} RMSE": scored[f"rmse_{axis}"], f"cov {axis}": scored[f"cover_{axis}"],
                f"cov {axis} focus": unscored[f"cover_{axis}"],
                f"need {axis}": needed_part(focus, axis),
                f"σ {axis}": float(used[f"{axis}_err_nm"].median()),
                f"field σ {axis}": float(np.nanmedian(field_sigma(cal, axis, z, distance))),
                }  # fmt: skip
    return row


def row_of(seed: int, size: str, renders: Path | None = None) -> dict:
    start = time.perf_counter()
    draw = draw_microscope(seed, size)
    row = {"seed": seed, "medium": draw.medium, "NA": round(draw.na, 2), "form": draw.form,
           "astig nm": round(draw.astigmatism_nm), "coma nm": coma(draw.mean_nm),
           "coma field nm": coma(draw.std_nm)}  # fmt: skip
    data = family_data(draw, renders=renders)
    cal, choices = calibrate_defaults(data.stacks, data.z_nm, data.camera)
    row |= choices
    if cal is not None:
        row |= study_row(data, cal)
    return row | {"total s": round(time.perf_counter() - start)}


LEGEND = (
    "`ref x`, `ref y`: the kept particles' position at z_f less their true place, RMS about a "
    "plane (nm); `smooth`: its part shared by nearest neighbours (nm); `part x`, `part y`: the "
    "part of σ that stands for it (nm); `cen r`, `cen k`: correlation of the offsets with the "
    "fitted centre less the intensity centroid within the depth of focus, and the factor from "
    "it to them (both 1 if the centroid lay at the place); RMSE and `cov` (share of |error| ≤ "
    "1σ) of the test spots after one plane per axis, `cov focus` without the part, `need`: the "
    "part that would make 1σ cover 68.27 % (nm); `σ`, `field σ`: medians over the spots of the "
    "reported σ and its field part (nm). Coma: RMS of the mean coma and of its variation over "
    "the field (nm)."
)


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> None:
    lines = [
        "# The particles' lateral reference against their places",
        "",
        f"Command: `python benchmarks/bench_lateral_reference.py --draws {args.draws} "
        f"--first {args.first} --size {args.size}` ({len(rows)} draws, {seconds / 60:.0f} min "
        "on a shared, loaded 2-core machine).",
        "",
        LEGEND,
        "",
        markdown(pd.DataFrame(rows)),
        "",
    ]
    write_text_atomic(args.out, "\n".join(lines))


def study(path: Path, out: Path) -> None:
    """One row for the study pickled at ``path``, calibrated with defaults, written to ``out``."""
    start = time.perf_counter()
    data = pickle.loads(path.read_bytes())
    cal, row = calibrate_defaults(data.stacks, data.z_nm, data.camera)
    if cal is not None:
        row |= study_row(data, cal)
    row["total s"] = round(time.perf_counter() - start)
    print(row, file=sys.stderr)
    lines = ["# The particles' lateral reference against their places", "",
             f"Command: `python benchmarks/bench_lateral_reference.py --study {path}`.", "",
             LEGEND, "", markdown(pd.DataFrame([row])), ""]  # fmt: skip
    write_text_atomic(out, "\n".join(lines))


def main() -> None:
    if "--study" in sys.argv:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
        parser.add_argument("--study", type=Path, required=True)
        parser.add_argument("--out", type=Path, default=OUT.with_name(OUT.stem + "_study.md"))
        args = parser.parse_args()
        warnings.simplefilter("ignore")
        study(args.study, args.out)
        return
    run_draws(__doc__.splitlines()[0], row_of, write, out=OUT, draws=4, first=0, size="ci")


if __name__ == "__main__":
    main()

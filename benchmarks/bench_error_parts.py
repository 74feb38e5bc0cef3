"""Benchmark: which part of ``z_err_nm`` is wrong, per draw of the random family of microscopes.

Each draw (:func:`latentz.validation.family.draw_microscope`) is calibrated with defaults only,
its test frames localized and scored against geometry (:mod:`latentz.validation.truth`). The
same test frames are imaged again without noise and localized alike. The actual z error of a
spot then splits into:

- **fit noise**: the noisy spot's error minus the noise-free spot's, which the fit's part of
  ``z_err_nm`` (``z_err_fit_nm``, the Cramér–Rao / sandwich errors of the spot's own fit) must
  cover;
- **systematic**: the noise-free spot's error (calibration model, field, dimming, the
  particles' heights), which the rest of ``z_err_nm`` must cover.

Each has one plane per draw removed, as the scoring does. ``k`` is the factor by which the
reported part is too small: the median of |error| / σ over 0.674 (1 where it is right; the
median of |error| for a normal error is 0.674 σ). The systematic k is also given for the
third of the spots farthest from their calibration particle and the third nearest, and for the
dimmer and the brighter half of the test emitters.

Writes ``results/bench_error_parts.md`` after every draw (atomically).

Run: ``python benchmarks/bench_error_parts.py [--first 4] [--draws 4] [--size small]``
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.validation.datasets import emitter_images
from latentz.validation.family import FAMILY_SIZES, draw_microscope, family_data
from latentz.validation.truth import localize_test, remove_planes, true_positions

sys.path.insert(0, str(Path(__file__).parent))
from _draws import run_draws  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_error_parts.md"
HALF_NORMAL_MEDIAN = 0.674


def raw_errors(data, located: pd.DataFrame) -> pd.DataFrame:
    """Errors (nm) of located spots against geometry, per (emitter, frame), no plane removed."""
    truth = true_positions(data)
    spots = located.drop_duplicates(["emitter", "frame"]).merge(
        truth, on=["emitter", "frame"], suffixes=("", "_true"))  # fmt: skip
    px = data.microscope.pixel_size_nm
    return pd.DataFrame({
        "emitter": spots["emitter"], "frame": spots["frame"],
        "x": spots["x_nm_true"] / px, "y": spots["y_nm_true"] / px,
        "in_range": spots["in_range"].to_numpy(bool),
        **{f"err_{a}_nm": spots[f"{a}_nm"] - spots[f"{a}_nm_true"] for a in "xyz"},
        **{c: spots[c] for c in ("z_err_nm", "z_err_fit_nm", "distance_px", "emitted")},
    })  # fmt: skip


def noise_free_spots(data, cal, size: str) -> pd.DataFrame:
    """The test frames imaged without noise, localized as the noisy ones."""
    n = data.frames.shape[-1]
    expected = emitter_images(data.microscope, data.fields, data.test_truth, (n, n),
                              data.background, FAMILY_SIZES[size]["patch_px"])  # fmt: skip
    frames = expected / data.camera.gain + data.camera.offset
    return localize_test(replace(data, frames=frames), calibration=cal)


def k_factor(err: np.ndarray, sigma: np.ndarray) -> float:
    """Median of |err| / sigma over that of a normal error (1: the reported σ is right)."""
    return float(np.median(np.abs(err) / sigma) / HALF_NORMAL_MEDIAN) if err.size else np.nan


def split(data, cal, size: str) -> pd.DataFrame:
    """Per in-range spot: the actual z error, its fit-noise and systematic parts (each with its
    own plane removed), the reported σ, its fit part and the rest."""
    emitted = data.test_truth[["emitter", "frame", "photons"]].rename(
        columns={"photons": "emitted"})  # fmt: skip

    def located(spots: pd.DataFrame) -> pd.DataFrame:
        out = cal.apply(spots, error_parts=True)
        out["distance_px"] = np.hypot(*(out[["x", "y"]].to_numpy(float)
                                        - cal.positions[out["cal_particle"]]).T)  # fmt: skip
        return out.merge(emitted, on=["emitter", "frame"])

    noisy = raw_errors(data, located(localize_test(data, calibration=cal)))
    clean = raw_errors(data, located(noise_free_spots(data, cal, size)))
    both = noisy.merge(clean[["emitter", "frame", "err_z_nm", "in_range"]],
                       on=["emitter", "frame"], suffixes=("", "_clean"))  # fmt: skip
    both = both[both["in_range"] & both["in_range_clean"]].copy()
    noise = both.assign(err_z_nm=both["err_z_nm"] - both["err_z_nm_clean"])
    systematic = both.assign(err_z_nm=both["err_z_nm_clean"])
    both["err"] = remove_planes(both)["err_z_nm"]
    both["noise"] = remove_planes(noise)["err_z_nm"]
    both["systematic"] = remove_planes(systematic)["err_z_nm"]
    both["sigma_rest"] = np.sqrt(np.maximum(both["z_err_nm"] ** 2 - both["z_err_fit_nm"] ** 2,
                                            0.0))  # fmt: skip
    return both


def row_of(seed: int, size: str, renders: Path | None = None) -> dict:
    """One draw's row: settings, coverage and the k factors of each part. ``renders``: a
    folder that keeps the draw's images (:func:`~latentz.validation.family.family_data`)."""
    from latentz.calibration import calibrate

    draw = draw_microscope(seed)
    row = {"seed": seed, "NA": round(draw.na, 2), "px nm": round(draw.pixel_size_nm),
           "form": draw.form, "bead nm": round(draw.bead_nm)}  # fmt: skip
    data = family_data(draw, size, renders=renders)
    try:
        cal = calibrate(data.stacks, data.z_nm, camera=data.camera)
    except ValueError as err:
        return row | {"fails": str(err).splitlines()[0][:120]}
    row |= {"ROI": cal.roi_size, "model": cal.field_model, "kept": int(cal.kept.size)}
    t = split(data, cal, size)
    far = t["distance_px"] >= t["distance_px"].quantile(2 / 3)
    near = t["distance_px"] <= t["distance_px"].quantile(1 / 3)
    dim = t["emitted"] < t["emitted"].median()
    k_sys = {name: k_factor(t.loc[m, "systematic"].to_numpy(), t.loc[m, "sigma_rest"].to_numpy())
             for name, m in (("", slice(None)), (" near", near), (" far", far), (" dim", dim),
                             (" bright", ~dim))}  # fmt: skip
    return row | {
        "spots": len(t), "cov z": float(np.mean(np.abs(t["err"]) <= t["z_err_nm"])),
        "noise nm": float(np.median(np.abs(t["noise"]))),
        "k fit": k_factor(t["noise"].to_numpy(), t["z_err_fit_nm"].to_numpy()),
        "sys nm": float(np.median(np.abs(t["systematic"]))),
        **{f"k sys{name}": value for name, value in k_sys.items()},
        "fails": "",
    }  # fmt: skip


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> None:
    table = pd.DataFrame(rows)

    def cell(value) -> str:
        if isinstance(value, float):
            return "" if np.isnan(value) else f"{value:.3g}"
        return str(value)

    out = "" if args.out == OUT else f" --out {args.out}"
    lines = [
        "# What z_err_nm is made of, on the random family of microscopes",
        "",
        f"Command: `python benchmarks/bench_error_parts.py --first {args.first} --draws "
        f"{args.draws} --size {args.size}{out}` ({len(rows)} draws, {seconds / 60:.0f} min "
        "on a 2-core machine).",
        "",
        "`k`: the factor by which each reported part is too small (median of |error| / σ over "
        "0.674); `k fit` for the fit noise against `z_err_fit_nm`, `k sys` for the noise-free "
        "spots' errors against the rest of `z_err_nm`; `noise nm`, `sys nm`: median |error|.",
        "",
        "| " + " | ".join(table.columns) + " |",
        "|" + "---|" * len(table.columns),
        *("| " + " | ".join(cell(v) for v in r) + " |" for r in table.itertuples(False)),
        "",
    ]
    write_text_atomic(args.out, "\n".join(lines))


def main() -> None:
    run_draws(__doc__.splitlines()[0], row_of, write, out=OUT, draws=4, first=4,
              size="small")


if __name__ == "__main__":
    main()

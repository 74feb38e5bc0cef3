"""Which part of the reported z error is too large or too small, and for which spots.

``python benchmarks/bench_coverage.py [--out benchmarks/results/bench_coverage.md]``

The two cases of ``tests/validation/test_coverage.py`` (latentz's simulator, 40 calibration
particles of 1 µm, 30 test particles at other places; the small independent validation
microscope), plus the simulator case with calibration particles of one size
(``diameter_sd_nm`` = 0 instead of the simulator's default 24 nm). For each: the 1σ coverage of
x, y, z; the actual z RMS against the reported one and its field part, by distance to the nearest
calibration particle and by |z|; and the split of the cross-validation's held-out z errors into
one constant offset per held-out particle and the rest, beside the same split of the test
emitters' actual errors (offset beyond what the within-emitter scatter explains).
"""

from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np
import pandas as pd

import latentz as lz
from latentz.calibration.field_errors import field_sigma

ROI = 15


def simulator_case(diameter_sd_nm: float) -> tuple:
    """(calibration, apply output, error table) of the coverage test's simulator case."""
    from latentz import simulate as sim
    from latentz.validation.accuracy import (
        error_table,
        focal_plane,
        focus_positions,
        localize_dataset,
    )

    field = (384, 384)
    common = {"n_stage_positions": 1, "frame_shape": field, "min_spacing_px": 40.0,
              "aberrations": sim.AberrationMap.default(seed=2, field_shape=field)}  # fmt: skip
    cal_ds = sim.calibration_dataset(n_particles=40, z_nm=np.linspace(-1500, 1500, 31), seed=2,
                                     diameter_sd_nm=diameter_sd_nm, **common)  # fmt: skip
    test_ds = sim.calibration_dataset(n_particles=30, z_nm=np.linspace(-1000, 1000, 9), seed=12,
                                      **common)  # fmt: skip
    cal = lz.calibrate(cal_ds.stacks, cal_ds.z_nm, camera=cal_ds.camera, shape="rho_w",
                       roi_size=ROI, field_model="zernike")  # fmt: skip
    # the lateral truth is the paper's (the fitted centre at best focus), as in the test
    located = cal.apply(localize_dataset(test_ds, roi_size=ROI), lateral_reference="focus")
    errors = error_table(located, test_ds, focal_plane(cal_ds.truth),
                         focus=focus_positions(test_ds, roi_size=ROI))  # fmt: skip
    keep = errors["in_range"].to_numpy(bool)
    errors = errors.assign(emitter=errors["particle"])
    return cal, located[keep].reset_index(drop=True), errors[keep].reset_index(drop=True)


def validation_case() -> tuple:
    """(calibration, apply output, error table) of the coverage test's validation case."""
    from latentz.validation import make_data
    from latentz.validation.truth import localize_test, score

    data = make_data("small", seed=1, n_frames=16)
    cal = lz.calibrate(data.stacks, data.z_nm, camera=data.camera, shape="rho_w", roi_size=ROI,
                       field_model="zernike")  # fmt: skip
    located = cal.apply(localize_test(data, roi_size=ROI))
    errors = score(data, located)
    errors = errors[errors["in_range"].to_numpy(bool)].reset_index(drop=True)
    located = errors[["emitter", "frame"]].merge(located, on=["emitter", "frame"], how="left")
    return cal, located, errors


def _rms(values) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _offsets(err: pd.Series, group: pd.Series) -> tuple[float, float, float]:
    """RMS of the per-group mean, of that mean beyond the within-group scatter over √n, and of
    the within-group rest (nm)."""
    g = err.groupby(group)
    mean, n, var = g.mean(), g.size(), g.var(ddof=1).fillna(0.0)
    beyond = float(np.mean(mean**2 - var / n))
    return _rms(mean), float(np.sqrt(max(beyond, 0.0))), _rms(err - g.transform("mean"))


def study(name: str, cal, located: pd.DataFrame, errors: pd.DataFrame) -> list[str]:
    """Markdown lines of one case."""
    x, y, z = (located[c].to_numpy(float) for c in ("x", "y", "z_nm"))
    p = cal.nearest(x, y)
    distance = np.hypot(x - cal.positions[p, 0], y - cal.positions[p, 1])
    lines = [f"## {name}", ""]
    cover = []
    for axis in "xyz":
        actual = errors[f"err_{axis}_nm"].to_numpy() - errors[f"err_{axis}_nm"].mean()
        cover.append(f"{axis} {100 * np.mean(np.abs(actual) <= located[f'{axis}_err_nm']):.1f} %")
    lines += [f"{len(errors)} spots; 1σ covers " + ", ".join(cover) + ".", ""]
    actual = errors["err_z_nm"].to_numpy() - errors["err_z_nm"].mean()
    reported = located["z_err_nm"].to_numpy()
    field = field_sigma(cal, "z", z, distance)
    spots = pd.DataFrame({"actual": actual, "reported": reported, "field": field,
                          "distance_px": distance, "abs_z_nm": np.abs(z)})  # fmt: skip
    for column, edges in (("distance_px", [0, 15, 25, 35, 1e3]),
                          ("abs_z_nm", [0, 250, 500, 750, 1e4])):  # fmt: skip
        lines += [f"| {column} | n | actual z RMS | reported | of which field | 1σ covers |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for interval, part in spots.groupby(pd.cut(spots[column], edges), observed=True):
            lines.append(
                f"| {interval} | {len(part)} | {_rms(part['actual']):.1f} | "
                f"{_rms(part['reported']):.1f} | {_rms(part['field']):.1f} | "
                f"{100 * np.mean(np.abs(part['actual']) <= part['reported']):.0f} % |"
            )
        lines.append("")
    table = cal.crossval_of(cal.field_model)
    held = table[(table["model"] == cal.field_model) & table["in_range"]]
    lines += ["| z errors within ±1 µm (nm RMS) | per-particle offset | offset beyond noise | "
              "rest |", "|---|---|---|---|"]  # fmt: skip
    near = held[held["z_nm"].abs() <= 1000]
    lines.append("| held-out calibration particles | {:.1f} | {:.1f} | {:.1f} |".format(
        *_offsets(near["err_z_nm"], near["particle"])))  # fmt: skip
    within = (errors["true_z_nm"].abs() <= 1000).to_numpy()
    lines.append("| test emitters, actual | {:.1f} | {:.1f} | {:.1f} |".format(
        *_offsets(pd.Series(actual[within]), errors["emitter"][within].to_numpy())))  # fmt: skip
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/bench_coverage.md")
    args = parser.parse_args()
    lines = ["# Where the reported z error is too large or too small", ""]
    for name, case in (
        ("latentz's simulator (the coverage test)", lambda: simulator_case(24.0)),
        ("latentz's simulator, calibration particles of one size", lambda: simulator_case(0.0)),
        ("independent validation microscope, small (the coverage test)", validation_case),
    ):
        part = study(name, *case())
        print("\n".join(part), flush=True)
        lines += part
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(args.out) or ".", suffix=".md")
    with os.fdopen(fd, "w") as handle:
        handle.write("\n".join(lines))
    os.replace(tmp, args.out)


if __name__ == "__main__":
    main()

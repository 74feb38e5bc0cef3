"""Benchmark: widefield accuracy and uncertainty coverage on the independent validation microscope.

Simulates issue 12's microscope with :mod:`latentz.validation` (other optics code, aberration
fields that are smooth random fields with a local defect, field curvature and tilt; NA 0.55,
640 nm, 130 nm pixels, 256 x 256 px; 128 beads in two stacks over ±3 µm in 50 nm steps at
2e5 photons; 600 spots of 60 point emitters within ±2 µm at 1e3-1e4 photons), calibrates with
every shape and field model (and the defaults), localizes the test frames with ``localize``
(the calibration's ROI) and reports against the truth:

- z RMSE, and lateral RMSE (x and y pooled) in 0.5 µm bands of |defocus|;
- the fraction of errors within 1σ of the reported ``x_err_nm``, ``y_err_nm``, ``z_err_nm``;
- the baseline of issue 12: the inverse-distance-weighted mean of the 4 nearest particles' own
  local models.

A-normalised shapes use each emitter's own reference amplitude (``amplitude_reference=
"particle"``, the emitters are of constant brightness). RMSEs are after one global offset per
axis. Writes ``results/bench_widefield_independent.md``.

Run: ``python benchmarks/bench_widefield_independent.py [--size small] [--cache FILE]
[--test-photons LO,HI] [--defaults]``. ``--defaults`` runs issue 12's "defaults only" study
(:func:`defaults_study`) and writes ``results/bench_widefield_independent_defaults*.md``.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.atomic import write_bytes_atomic
from latentz.calibration import calibrate, calibrate_traces
from latentz.calibration.placing import track_reference
from latentz.calibration.shape import shape_value, uses_amplitude
from latentz.validation import SIZES, make_data
from latentz.validation.datasets import emitter_images
from latentz.validation.truth import localize_test, score

OUT = Path(__file__).resolve().parent / "results"
SHAPES = ("rho", "rho_w", "rho_A", "auto", "auto_A")
KINDS = ("nearest", "natural", "curves", "zernike")
BANDS_NM = (0.0, 500.0, 1000.0, 1500.0, 2000.0)
ROI = 15


def _centred_rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean((values - values.mean()) ** 2))) if values.size else np.nan


def summarise(errors: pd.DataFrame) -> dict[str, float]:
    """RMSEs (one global offset removed per axis), by band, and 1σ coverage."""
    used = errors[errors["in_range"]].copy()
    for axis in "xyz":
        used[f"err_{axis}_nm"] -= used[f"err_{axis}_nm"].mean()
    row = {"spots": len(used), "in range": float(errors["in_range"].mean())}
    row["z"] = _centred_rms(used["err_z_nm"])
    lateral = np.concatenate([used["err_x_nm"], used["err_y_nm"]])
    row["xy"] = float(np.sqrt(np.mean(lateral**2)))
    band = np.abs(used["true_z_nm"].to_numpy())
    for lo, hi in zip(BANDS_NM[:-1], BANDS_NM[1:], strict=True):
        sel = (band >= lo) & (band < hi)
        row[f"z {lo / 1000:.1f}-{hi / 1000:.1f}"] = float(
            np.sqrt(np.mean(used["err_z_nm"][sel] ** 2))
        )
    for lo, hi in zip(BANDS_NM[:-1], BANDS_NM[1:], strict=True):
        sel = (band >= lo) & (band < hi)
        both = np.concatenate([used["err_x_nm"][sel], used["err_y_nm"][sel]])
        row[f"xy {lo / 1000:.1f}-{hi / 1000:.1f}"] = float(np.sqrt(np.mean(both**2)))
    for axis in "xyz":
        err, sigma = np.abs(used[f"err_{axis}_nm"]), used[f"{axis}_err_nm"]
        row[f"cov {axis}"] = float(np.mean(err <= sigma)) if sigma.notna().any() else np.nan
    return row


def idw_baseline(cal, spots: pd.DataFrame, k: int = 4) -> pd.DataFrame:
    """Issue 12's baseline: z and Δx', Δy' as the inverse-distance-weighted mean over the ``k``
    nearest kept particles of their own local models (only those covering the spot's s)."""
    cols = {c: spots[c].to_numpy(float) for c in ("x", "y", "wx", "wy", "rho", "amplitude")}
    theta = cal.local.theta
    model = cal.local.shapes[cal.shape]
    if uses_amplitude(cal.shape):
        ref = track_reference(cal.shape, spots, cols, theta)
    else:
        ref = np.ones(len(spots))
    s = shape_value(cal.shape, cols["wx"], cols["wy"], cols["rho"], cols["amplitude"],
                    theta=theta, amplitude_ref=ref)  # fmt: skip
    kept = cal.kept
    pos = cal.positions[kept]
    dist = np.hypot(cols["x"][:, None] - pos[:, 0], cols["y"][:, None] - pos[:, 1])
    near = np.argsort(dist, axis=1)[:, :k]
    z_k, w_k = np.full(near.shape, np.nan), np.zeros(near.shape)
    for j in range(k):
        p = kept[near[:, j]]
        inv = model.inverse[p]
        ok = inv.contains(s) & inv.valid
        z_k[:, j] = np.where(ok, inv(np.where(ok, s, 0.0)), np.nan)
        w_k[:, j] = np.where(ok, 1.0 / np.maximum(dist[np.arange(len(s)), near[:, j]], 1e-3), 0)
    z = np.nansum(z_k * w_k, axis=1) / w_k.sum(axis=1)
    dx, dy = np.zeros(len(s)), np.zeros(len(s))
    for j in range(k):
        p = kept[near[:, j]]
        zq = np.where(np.isfinite(z), z, 0.0)
        dx += w_k[:, j] * cal.local.dx[p](zq)
        dy += w_k[:, j] * cal.local.dy[p](zq)
    px = cal.camera.pixel_size_nm
    total = w_k.sum(axis=1)
    ok = total > 0
    out = spots.copy()
    out["z_nm"] = np.where(ok, z, np.nan)
    out["x_nm"] = np.where(ok, (cols["x"] - dx / np.maximum(total, 1e-12)) * px, np.nan)
    out["y_nm"] = np.where(ok, (cols["y"] - dy / np.maximum(total, 1e-12)) * px, np.nan)
    for axis in "xyz":
        out[f"{axis}_err_nm"] = np.nan
    out["in_range"] = ok
    return out


def noise_free_spots(
    data, size: str, photons: float | None = None, roi_size: int = ROI
) -> pd.DataFrame:
    """``localize_test`` on the test frames without noise (ADU), every emitter with its own
    photons or with ``photons``."""
    truth = data.test_truth if photons is None else data.test_truth.assign(photons=photons)
    images = emitter_images(data.microscope, data.fields, truth, data.frames.shape[1:],
                            data.background, SIZES[size]["patch_px"])  # fmt: skip
    clean = replace(data, frames=images / data.camera.gain + data.camera.offset)
    return localize_test(clean, roi_size=roi_size)


def error_budget(cal, data, spots: pd.DataFrame, size: str) -> pd.DataFrame:
    """Where the z error of ``cal.apply(spots)`` comes from, in bins of the emitters' photons.

    The actual error (noisy spot minus truth) is split into: *noise*, the noisy spot minus the
    same spot without noise; *photon bias*, the noise-free spot at its own photons minus at the
    calibration's photons (a Gaussian fitted to a non-Gaussian PSF finds other widths when its
    wings sink into the background); *field and bead bias*, the noise-free spot at the
    calibration's photons minus truth (field model, point emitter against bead). Beside them,
    the RMS of the reported parts: the fit's Cramér–Rao part and the field part.
    """
    key = ["emitter", "frame"]
    z = {}
    for name, photons in (
        ("noisy", None),
        ("clean", None),
        ("bright", data.calibration_truth["photons"].iloc[0]),
    ):
        found = spots if name == "noisy" else noise_free_spots(data, size, photons)
        matched = spots[key].merge(found.drop(columns="particle", errors="ignore"), on=key,
                                   how="left")  # fmt: skip
        z[name] = cal.apply(matched)["z_nm"].to_numpy()
    errors = score(data, cal.apply(spots))
    actual = errors["err_z_nm"].to_numpy()
    true_z = z["noisy"] - actual
    parts = pd.DataFrame({"photons": spots["photons"].to_numpy(), "actual": actual,
                          "noise": z["noisy"] - z["clean"], "photon bias": z["clean"] - z["bright"],
                          "field and bead bias": z["bright"] - true_z,
                          "reported": errors["z_err_nm"].to_numpy()})  # fmt: skip
    parts = parts[np.all(np.isfinite(parts.to_numpy()), axis=1)]
    parts["actual"] -= parts["actual"].mean()
    parts["field and bead bias"] -= parts["field and bead bias"].mean()
    bins = pd.cut(parts["photons"], [0, 1.5e3, 3e3, 6e3, 1.5e4, 5e4, np.inf])
    rms = (
        parts.drop(columns="photons")
        .groupby(bins, observed=True)
        .agg(lambda v: float(np.sqrt(np.mean(v**2))))
    )
    rms["n"] = parts.groupby(bins, observed=True).size()
    rms["cov z"] = (parts["actual"].abs() <= parts["reported"]).groupby(bins, observed=True).mean()
    return rms.rename_axis("fitted photons").reset_index().astype({"fitted photons": str})


def load_study(size: str, cache: Path | None, seed: int = 0,
               test_photons: tuple[float, float] = (1e3, 1e4)):  # fmt: skip
    """The validation data, from ``cache`` when it exists."""
    if cache is not None and cache.exists():
        with cache.open("rb") as f:
            return pickle.load(f)
    data = make_data(size, seed=seed, test_photons=test_photons)
    if cache is not None:
        write_bytes_atomic(cache, pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL))
    return data


def every_model(data, shapes: list[str], size: str) -> str:
    """Every shape x field model (and ``auto``) at a 15 px ROI, the IDW baseline, and the error
    budget of ``rho_w`` + ``auto``: the markdown text of the results file."""
    spots = localize_test(data, roi_size=ROI).assign(particle=lambda f: f["emitter"])
    first = calibrate(data.stacks, data.z_nm, camera=data.camera, shape="rho_w",
                      field_model="nearest", roi_size=ROI)  # fmt: skip
    rows = []
    for shape in shapes:
        reference = "particle" if uses_amplitude(shape) else "calibration"
        for kind in (*KINDS, "auto"):
            try:
                cal = calibrate_traces(first.traces, camera=data.camera, shape=shape,
                                       field_model=kind, roi_size=ROI,
                                       field_shape=first.options["field_shape"])  # fmt: skip
            except ValueError as err:  # e.g. a field model this version does not have
                print(f"{shape} {kind}: {err}")
                continue
            located = cal.apply(spots, amplitude_reference=reference)
            chosen = cal.field_model if kind == "auto" else ""
            if kind == "auto" and shape == "rho_w":
                budget = error_budget(cal, data, spots, size)
            row = {"shape": shape, "field model": kind + (f" ({chosen})" if chosen else "")}
            rows.append(row | summarise(score(data, located)))
        base = calibrate_traces(first.traces, camera=data.camera, shape=shape,
                                field_model="nearest", roi_size=ROI,
                                field_shape=first.options["field_shape"])  # fmt: skip
        located = idw_baseline(base, spots)
        rows.append({"shape": shape, "field model": "IDW 4-nearest baseline"}
                    | summarise(score(data, located)))  # fmt: skip
    table = pd.DataFrame(rows)
    text = table.to_markdown(index=False, floatfmt=".3g")
    if "budget" in locals():
        text += (
            "\n\nWhere the z error comes from (`rho_w`, `auto`; RMS in nm by fitted photons; "
            "see `error_budget`: noise = noisy minus noise-free spot, photon bias = noise-free "
            "at its own photons minus at the calibration's, field and bead bias = noise-free at "
            "the calibration's photons minus truth; reported = `z_err_nm`):\n\n"
            + budget.to_markdown(index=False, floatfmt=".3g")
        )
    return text


TRANSFER_GRID_NM = np.arange(-2800.0, 2800.1, 20.0)


def _shape_of(cal, fits: pd.DataFrame) -> np.ndarray:
    """The calibration's shape value of ``fits`` (a shape not normalised by amplitude)."""
    return shape_value(cal.shape, fits["wx"].to_numpy(), fits["wy"].to_numpy(),
                       fits["rho"].to_numpy(), fits["amplitude"].to_numpy(),
                       theta=cal.local.theta, amplitude_ref=np.ones(len(fits)))  # fmt: skip


def _focus_run(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) nm of the monotonic run of each row of ``curves`` on the transfer grid that
    holds defocus 0."""
    grid = TRANSFER_GRID_NM
    slope = np.sign(np.diff(curves, axis=1))
    i0 = int(np.argmin(np.abs(grid)))
    idx = np.arange(slope.shape[1])
    brk = slope != slope[:, i0 : i0 + 1]
    left = np.max(np.where(brk & (idx < i0), idx, -1), axis=1) + 1
    right = np.min(np.where(brk & (idx > i0), idx, slope.shape[1]), axis=1)
    return grid[left], grid[right]


def curve_transfer(data, cal, spots: pd.DataFrame) -> str:
    """How well each way of carrying curves across the field could do, with exact curves.

    Noise-free point emitters (1e5 photons, alone, fitted in the calibration's ROI) are rendered
    through focus at every kept bead's position and every test emitter's, in defocus from the
    focal surface (no z = 0 convention, no calibration noise). Each emitter's own curve, inverted
    at its own s over |defocus| <= 2 µm, is then compared with the z that the beads' curves give
    it: the nearest bead's, the Sibson mean of the natural neighbours' z at fixed s (the former
    ``curves``), the Sibson mean of their s at fixed z, and a thin-plate spline of s at fixed z
    (``curves`` now). Also the test spots inverted on their emitter's own curve at its own
    brightness (no field model at all), and the order-16 local models against the beads' own
    noise-free images. RMS in nm after one global offset. Markdown text.
    """
    from scipy.interpolate import RBFInterpolator

    from latentz.calibration.fieldmodels import field_weights
    from latentz.calibration.widefield import crossing
    from latentz.validation.floor import bead_fits, emitter_fits

    if uses_amplitude(cal.shape):
        return "(skipped: an amplitude-normalised shape)"
    grid, roi = TRANSFER_GRID_NM, cal.roi_size
    beads = cal.positions[cal.kept]
    emitters = data.test_truth.drop_duplicates("emitter").set_index("emitter")
    curve = {}
    for name, xy, photons in (
        ("bead", beads, np.full(len(beads), 1e5)),
        ("emitter", emitters[["x", "y"]].to_numpy(), np.full(len(emitters), 1e5)),
        ("own", emitters[["x", "y"]].to_numpy(), emitters["photons"].to_numpy()),
    ):
        curve[name] = np.array([_shape_of(cal, emitter_fits(data, x, y, grid, roi_size=roi,
                                                            photons=n))
                                for (x, y), n in zip(xy, photons, strict=True)])  # fmt: skip
    near = np.abs(grid) <= 2000.0
    k, m = len(emitters), int(near.sum())
    s = curve["emitter"][:, near].ravel()
    rows = np.repeat(np.arange(k), m)
    true = np.tile(grid[near], k)

    def run_of(curves: np.ndarray, which: np.ndarray) -> np.ndarray:
        lo, hi = _focus_run(curves)
        return crossing(grid, curves[which], s, lo[which], hi[which])

    q, p, w, _ = field_weights(beads, emitters[["x", "y"]].to_numpy(), "curves")
    sibson = np.zeros((k, len(beads)))
    sibson[q, p] = w
    nearest = cKDTree(beads).query(emitters[["x", "y"]].to_numpy())[1]
    z_each = np.array([run_of(curve["bead"], np.full(k * m, b)) for b in range(len(beads))])
    weight = sibson[rows].T * np.isfinite(z_each)
    rows_z = {
        "own curve (1e5 photons)": run_of(curve["emitter"], rows),
        "nearest bead's curve": z_each[nearest[rows], np.arange(k * m)],
        "Sibson mean of z at fixed s (former `curves`)": np.nansum(z_each * weight, axis=0)
        / weight.sum(axis=0),
        "Sibson mean of s at fixed z": run_of(sibson @ curve["bead"], rows),
        "thin-plate spline of s at fixed z (`curves`)": run_of(
            RBFInterpolator(beads, curve["bead"], kernel="thin_plate_spline")(
                emitters[["x", "y"]].to_numpy()
            ),
            rows,
        ),  # fmt: skip
    }
    lines = [
        {"curve used for the emitter": name, "z RMSE": _centred_rms(z - true),
         "not found": float(np.mean(~np.isfinite(z)))}
        for name, z in rows_z.items()
    ]  # fmt: skip
    table = pd.DataFrame(lines).to_markdown(index=False, floatfmt=".3g")
    # the test spots on their emitter's own curve at its own brightness
    e = spots["emitter"].to_numpy()
    index = emitters.index.get_indexer(e)
    lo, hi = _focus_run(curve["own"])
    z = crossing(grid, curve["own"][index], _shape_of(cal, spots), lo[index], hi[index])
    key = data.test_truth.set_index(["emitter", "frame"])["defocus_nm"]
    true_spot = key.loc[list(zip(e, spots["frame"], strict=True))].to_numpy()
    own = _centred_rms(z - true_spot)
    # the order-16 local models against the beads' own noise-free images (within 0.5 µm of focus)
    model = cal.local.shapes[cal.shape]
    bead_truth = data.calibration_truth
    match = cKDTree(bead_truth[["x", "y"]].to_numpy()).query(beads)[1]
    misfit, noise = [], []
    for p_, j in zip(cal.kept, match, strict=True):
        clean = _shape_of(cal, bead_fits(data, j, roi_size=roi))
        zp = cal.local.z_nm[p_]
        focus = np.abs(zp - cal.local.z_f[p_]) <= 500.0
        misfit.append((model.forward[p_](zp[None])[0] - clean)[focus])
        noise.append((model.values[p_] - clean)[focus])
    misfit, noise = np.concatenate(misfit), np.concatenate(noise)
    return (
        table
        + f"\n\nThe test spots on their emitter's own exact curve at its own brightness (no field "
        f"model): z RMSE {own:.3g} nm ({np.isfinite(z).sum()} of {len(z)} spots found). Within "
        f"0.5 µm of focus the order-16 forward models s(z) miss the beads' noise-free shape "
        f"values by {np.sqrt(np.nanmean(misfit**2)):.3g} RMS; the measured values by "
        f"{np.sqrt(np.nanmean(noise**2)):.3g} (their noise)."
    )


def defaults_study(data, size: str, cache: Path | None) -> tuple[str, dict[str, str]]:
    """Issue 12's "defaults only" study: ``calibrate`` with no shape, ROI or field model, the
    test frames localized with ``localize(calibration=cal)`` (its ROI, shape and model), beside
    ``nearest`` and the inverse-distance baseline at the same shape and ROI, and the defaults
    without the particles' own lateral reference (``apply(lateral_reference="focus")``).

    Returns the text (a table with one row per model: the scores of :func:`summarise`,
    ``z / nearest``, and the z RMSE of the same spots without noise, ``z noise-free``; then
    :func:`curve_transfer`) and what calibrate chose.
    """
    cal = calibrate(data.stacks, data.z_nm, camera=data.camera)
    roi = cal.roi_size
    spots = localize_test(data, calibration=cal)
    near = calibrate_traces(cal.traces, camera=data.camera, shape=cal.shape,
                            field_model="nearest", roi_size=roi,
                            field_shape=cal.options["field_shape"])  # fmt: skip
    clean = noise_free_spots(data, size, roi_size=roi)
    models = {
        f"defaults: {cal.field_model}": cal.apply,
        "nearest": near.apply,
        "IDW 4-nearest baseline": lambda frame: idw_baseline(near, frame),
        # σ without the particles' own lateral reference (docs/accuracy.md, part 4)
        "defaults, lateral_reference='focus'": lambda frame: cal.apply(
            frame, lateral_reference="focus"
        ),
    }
    rows = []
    for name, apply in models.items():
        row = {"field model": name} | summarise(score(data, apply(spots)))
        row["z noise-free"] = summarise(score(data, apply(clean)))["z"]
        rows.append(row)
    table = pd.DataFrame(rows)
    table.insert(3, "z / nearest", table["z"] / table.loc[1, "z"])
    choice = cal.shape_choice or {}
    chosen = {
        "ROI": f"{roi} px",
        "shape": cal.shape + (f" ({choice.get('reason')})" if choice.get("reason") else ""),
        "field model": cal.field_model,
        "kept particles": f"{cal.kept.size} of {len(cal.positions)}",
        "particles' own lateral reference x / y": f"{cal.reference_sigma_nm('x'):.1f} / "
        f"{cal.reference_sigma_nm('y'):.1f} nm",
    }
    text = (
        table.to_markdown(index=False, floatfmt=".3g")
        + "\n\nCarrying curves across the field, with exact curves (`curve_transfer`):\n\n"
        + curve_transfer(data, cal, spots)
    )
    return text, chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="full", choices=("full", "small"))
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--shapes", default=",".join(SHAPES))
    parser.add_argument(
        "--test-photons",
        default="1e3,1e4",
        help="photon range of the test emitters (log-uniform), e.g. 2e4,2e5",
    )
    parser.add_argument(
        "--defaults",
        action="store_true",
        help="calibrate and localize with defaults only (ROI, shape, field model from the data), "
        "beside nearest at the same shape and ROI",
    )
    args = parser.parse_args()
    test_photons = tuple(float(v) for v in args.test_photons.split(","))
    if len(test_photons) != 2 or not 0 < test_photons[0] <= test_photons[1]:
        parser.error(f"--test-photons: expected LO,HI with 0 < LO <= HI, got {args.test_photons!r}")
    if args.cache is not None and not args.cache.parent.is_dir():
        parser.error(f"--cache: the folder {args.cache.parent} does not exist; create it first")
    warnings.simplefilter("ignore", UserWarning)
    start = time.perf_counter()
    data = load_study(args.size, args.cache, test_photons=test_photons)
    made = time.perf_counter() - start
    if args.defaults:
        text, chosen = defaults_study(data, args.size, args.cache)
        for key, value in chosen.items():
            print(f"{key}: {value}")
        text = (
            "Chosen by `calibrate`: "
            + "; ".join(f"{k} {v}" for k, v in chosen.items())
            + (".\n\n" + text)
        )
    else:
        text = every_model(data, args.shapes.split(","), args.size)
    print(text)
    OUT.mkdir(exist_ok=True)
    header = (
        "# Widefield accuracy on the independent validation microscope\n\n"
        f"`python benchmarks/bench_widefield_independent.py {' '.join(sys.argv[1:])}` "
        f"(data and truth: {made:.0f} s; total {time.perf_counter() - start:.0f} s on a shared "
        f"machine). Test spots of {data.test_truth['emitter'].nunique()} point emitters; "
        f"{len(data.calibration_truth)} calibration beads; test emitters of "
        f"{test_photons[0]:g}-{test_photons[1]:g} photons. RMSE in nm after one global offset "
        "per axis; `z a-b`: z RMSE for a <= |true z| < b µm (same offset); `xy a-b`: lateral "
        "RMSE (x and y pooled) for a <= |true z| < b µm; `cov`: "
        "fraction of errors within the reported 1σ.\n\n"
    )
    suffix = "" if args.size == "full" else f"_{args.size}"
    if test_photons != (1e3, 1e4):
        suffix += f"_photons_{test_photons[0]:.0e}_{test_photons[1]:.0e}".replace("+0", "")
    if args.defaults:
        suffix = f"_defaults{suffix}"
    (OUT / f"bench_widefield_independent{suffix}.md").write_text(header + text + "\n")


if __name__ == "__main__":
    main()

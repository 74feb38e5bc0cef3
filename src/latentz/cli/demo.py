"""``latentz demo``: the whole job on built-in simulated data, compared with ground truth.

Simulates a microscope like the paper's (NA 0.55 air, 50x, intrinsic field-dependent aberrations),
then runs every stage as a user would: aperture array -> pixel size; calibration stacks ->
calibration; gear movie -> localize -> link -> rigid motion in six degrees of freedom -> Monte
Carlo uncertainty and Table 1; and writes ``report.html`` with every figure and the comparison
with truth.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz._shared.figures import figure_png
from latentz.report import Section, write_report
from latentz.report.sections import DOF_NAMES
from latentz.validation.accuracy import error_figure, focal_plane, rmse

if TYPE_CHECKING:
    from latentz.calibration import Calibration
    from latentz.camera import Camera
    from latentz.simulate import AberrationMap, CalibrationDataset, GearMovie, Optics

__all__ = ["DemoSize", "run_demo"]


@dataclass(frozen=True)
class DemoSize:
    """How big the simulated job is."""

    field_px: int
    stage_positions: int
    cal_particles: int
    z_half_range_nm: float
    z_step_nm: float
    gear_cycles: int
    gear_particles: int
    gear_diameter_um: float
    static_frames: int
    n_sim: int
    field_model: str


#: ROI side (pixels) for calibration and localization: a 1 µm particle 2 µm from focus has
#: widths of about 4.5 px at NA 0.55 and 130 nm pixels; a 15 px ROI truncates it (widefield
#: study: 2.3 nm lateral error at 21 px against 4.2 nm at 15 px).
ROI_PX = 21

FULL = DemoSize(2048, 16, 320, 3000.0, 50.0, 72, 28, 328.0, 5, 10000, "zernike")
QUICK = DemoSize(1024, 4, 80, 2000.0, 100.0, 6, 12, 120.0, 3, 500, "zernike")


def _timed(log: list[str], label: str, start: float) -> float:
    now = time.perf_counter()
    log.append(f"{label}: {now - start:.1f} s")
    return now


def _match_truth(locs: pd.DataFrame, truth: pd.DataFrame, *, max_px: float = 3.0) -> pd.DataFrame:
    """Pair each localization with the nearest true particle of its frame (within ``max_px``)."""
    from scipy.spatial import cKDTree

    rows = []
    for frame, group in locs.groupby("frame"):
        true = truth[truth["frame"] == frame]
        if true.empty:
            continue
        dist, idx = cKDTree(true[["x", "y"]].to_numpy()).query(group[["x", "y"]].to_numpy())
        keep = dist <= max_px
        pair = group[keep].copy()
        matched = true.iloc[idx[keep]]
        for col in ("particle", "x_nm", "y_nm", "field_x", "field_y", "defocus_nm"):
            pair[f"true_{col}"] = matched[col].to_numpy()
        rows.append(pair)
    return pd.concat(rows, ignore_index=True) if rows else locs.iloc[:0]


def _errors(
    pairs: pd.DataFrame, pixel_nm: float, centre_px: tuple[float, float], plane: np.ndarray
) -> pd.DataFrame:
    """Errors (nm) of corrected and uncorrected positions (one global offset is removed when
    they are summarised).

    The true axial position is the particle's defocus (height + piezo) minus the plane of best
    fit to the calibration particles' true best focus (``plane``, see
    :func:`latentz.validation.accuracy.focal_plane`): the calibrated z axis keeps the field
    curvature but
    not its planar part, which cannot be told apart from a substrate tilt.
    """
    ok = pairs["in_range"].to_numpy(bool)
    p = pairs[ok]
    true_x = p["true_x_nm"].to_numpy()
    true_y = p["true_y_nm"].to_numpy()
    fx, fy = p["true_field_x"].to_numpy(), p["true_field_y"].to_numpy()
    true_z = p["true_defocus_nm"].to_numpy() - (plane[0] + plane[1] * fx + plane[2] * fy)
    raw_x = (p["x"].to_numpy() - centre_px[0]) * pixel_nm
    raw_y = (p["y"].to_numpy() - centre_px[1]) * pixel_nm
    return pd.DataFrame(
        {
            "frame": p["frame"].to_numpy(),
            "true_x_nm": true_x,
            "true_y_nm": true_y,
            "true_z_nm": true_z,
            "err_x_nm": p["x_nm"].to_numpy() - true_x,
            "err_y_nm": p["y_nm"].to_numpy() - true_y,
            "err_z_nm": p["z_nm"].to_numpy() - true_z,
            "x_err_nm": p["x_err_nm"].to_numpy(),
            "y_err_nm": p["y_err_nm"].to_numpy(),
            "z_err_nm": p["z_err_nm"].to_numpy(),
            "raw_err_x_nm": raw_x - true_x,
            "raw_err_y_nm": raw_y - true_y,
            "in_range": True,
        }
    )


def _scale_removed(errors: pd.DataFrame, prefix: str = "") -> pd.DataFrame:
    """Lateral errors (nm) after one offset per axis and one common scale: what remains once
    the magnification's own error (from the aperture array) is taken out."""
    x, y = errors["true_x_nm"].to_numpy(), errors["true_y_nm"].to_numpy()
    ex, ey = errors[f"{prefix}err_x_nm"].to_numpy(), errors[f"{prefix}err_y_nm"].to_numpy()
    n = len(x)
    design = np.zeros((2 * n, 3))
    design[:n, 0], design[n:, 1] = 1.0, 1.0
    design[:, 2] = np.r_[x, y]
    values = np.r_[ex, ey]
    resid = values - design @ np.linalg.lstsq(design, values, rcond=None)[0]
    return errors.assign(**{f"{prefix}err_x_nm": resid[:n], f"{prefix}err_y_nm": resid[n:]})


def _rms_after_scale(errors: pd.DataFrame, prefix: str = "") -> tuple[float, float]:
    """Lateral RMS errors (nm) of :func:`_scale_removed`."""
    scaled = _scale_removed(errors, prefix)
    return _rms(scaled[f"{prefix}err_x_nm"]), _rms(scaled[f"{prefix}err_y_nm"])


def _truth_table(within: pd.DataFrame) -> pd.DataFrame:
    """The motion-against-truth table for the report: angles in mrad, with units."""
    angle = within["dof"].isin(["gamma", "beta", "alpha"]).to_numpy()
    scale = np.where(angle, 1e3, 1.0)
    return pd.DataFrame(
        {
            "degree of freedom": within["dof"].map(DOF_NAMES),
            "unit": np.where(angle, "mrad", "nm"),
            "RMS error": within["rms_error"] * scale,
            "σ (68 % half-width)": within["sigma"] * scale,
            "standard deviation": within["std"] * scale,
            "RMS of error / cycle's σ": within["rms_error_over_cycle_sigma"],
            "within the cycle's 1σ (%)": 100 * within["fraction_within_1_sigma"],
        }
    )


def _rms(values: pd.Series) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def run_demo(
    out_dir: str | os.PathLike = "demo-run",
    *,
    quick: bool = False,
    seed: int = 0,
    progress: bool = True,
) -> list[str]:
    """Run the demo into ``out_dir``; return summary lines (also in the report)."""
    import matplotlib

    matplotlib.use("Agg")
    from latentz.io import write_table

    size = QUICK if quick else FULL
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log: list[str] = []  # results
    timings: list[str] = []  # seconds per step
    start = t0 = time.perf_counter()
    scope = _microscope(size, seed)
    camera, aperture_cal = _apertures(scope, size, seed, log)
    t0 = _timed(timings, "apertures", t0)
    stacks = _calibration_stacks(scope, size, seed)
    t0 = _timed(timings, "simulate calibration", t0)
    cal = _calibrate_stacks(stacks, camera, size, progress, log)
    cal.save(out / "calibration.h5")
    t0 = _timed(timings, "calibrate", t0)
    gear, static_frames = _gear(scope, size, seed)
    t0 = _timed(timings, "simulate gear", t0)
    locs = _localize_3d(gear.frames, cal, camera, gear.origin, progress)
    static = _localize_3d(static_frames, cal, camera, gear.origin, progress)
    write_table(locs, out / "locs.parquet")
    t0 = _timed(timings, "localize", t0)
    errors = _localization_errors(locs, gear, stacks, camera.pixel_size_nm, log)
    write_table(errors, out / "errors_vs_truth.csv")
    tables, within = _motion(locs, static, gear, size, seed, out, log)
    t0 = _timed(timings, "track", t0)
    summary = "\n\n".join(log) + "\n\nTime per step: " + "; ".join(timings) + "."
    parts = [
        _calibration_quality(cal, errors),
        Section("Summary of the simulated run", summary),
        _psf_section(scope),
        *_calibration_sections(cal, aperture_cal),
        *_localization_sections(locs, errors),
        *_motion_sections(tables, within),
    ]
    write_report(
        [p for p in parts if p is not None],
        out / "report.html",
        title=f"latentz demo ({'quick' if quick else 'full'}, seed {seed}): {out.resolve().name}",
        png_dir=out / "figures",
    )
    _timed(timings, "report", t0)
    log.append("time per step: " + "; ".join(timings))
    log.append(f"total: {time.perf_counter() - start:.1f} s; report: {out / 'report.html'}")
    return log


@dataclass(frozen=True)
class _Microscope:
    """The simulated microscope: its optics and field-dependent aberrations, the camera as
    the user knows it (nominal 130 nm pixel), and the true sample pixel (nm)."""

    optics: Optics
    aberrations: AberrationMap
    nominal: Camera
    true_pixel_nm: float


def _microscope(size: DemoSize, seed: int) -> _Microscope:
    """A microscope like the paper's over the demo's field."""
    from latentz import simulate as sim
    from latentz.camera import Camera

    field = (size.field_px, size.field_px)
    true_pixel_nm = 129.3  # the sample pixel the aperture array measures (nominal 130 nm)
    return _Microscope(
        optics=sim.Optics(magnification=6.5e3 / true_pixel_nm),
        aberrations=sim.AberrationMap.default(seed=seed, field_shape=field),
        nominal=Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=130.0),
        true_pixel_nm=true_pixel_nm,
    )


def _apertures(
    scope: _Microscope, size: DemoSize, seed: int, log: list[str]
) -> tuple[Camera, Calibration]:
    """An aperture array of known pitch through focus: the camera with the pixel size from its
    lattice in focus, and (Supp. Fig. 9) its own calibration, whose field dependence differs
    from the particles'."""
    from latentz import simulate as sim
    from latentz.calibration import ApertureLattice, calibrate
    from latentz.camera import Camera
    from latentz.localization import localize

    aperture_z = np.arange(-2000.0, 2001.0, 2 * size.z_step_nm)
    apertures = sim.aperture_array(
        pitch_nm=5000.0,
        shape=(256, 256),
        pixel_size_nm=scope.true_pixel_nm,
        z_nm=aperture_z,
        optics=scope.optics,
        aberrations=scope.aberrations,
        camera=scope.nominal,
        seed=seed,
    )
    in_focus = int(np.argmin(np.abs(aperture_z)))
    spots = localize(apertures.frames[in_focus : in_focus + 1], camera=scope.nominal, roi_size=9)
    lattice = ApertureLattice.from_estimate(spots["x"], spots["y"], pitch_nm=5000.0)
    pixel_nm = float(lattice.pixel_size_nm)
    nominal = scope.nominal
    camera = Camera(
        offset=nominal.offset,
        gain=nominal.gain,
        readnoise=nominal.readnoise,
        pixel_size_nm=pixel_nm,
    )
    log.append(
        f"pixel size {pixel_nm:.3f} ± {lattice.pixel_size_err_nm:.3f} nm "
        f"(true {scope.true_pixel_nm} nm, error "
        f"{100 * (pixel_nm / scope.true_pixel_nm - 1):+.3f} %)"
    )
    aperture_cal = calibrate(
        apertures.frames,
        aperture_z,
        camera=camera,
        shape="rho_A",
        field_model="nearest",
        roi_size=ROI_PX,
        stage_offsets_px=[apertures.origin[::-1]],
    )
    return camera, aperture_cal


def _calibration_stacks(scope: _Microscope, size: DemoSize, seed: int) -> CalibrationDataset:
    """Calibration stacks through focus at several stage positions."""
    from latentz import simulate as sim

    z_nm = np.arange(-size.z_half_range_nm, size.z_half_range_nm + 1, size.z_step_nm)
    return sim.calibration_dataset(
        n_particles=size.cal_particles,
        z_nm=z_nm,
        n_stage_positions=size.stage_positions,
        optics=scope.optics,
        aberrations=scope.aberrations,
        camera=scope.nominal,
        seed=seed,
    )


def _calibrate_stacks(
    stacks: CalibrationDataset, camera: Camera, size: DemoSize, progress: bool, log: list[str]
) -> Calibration:
    """The calibration from the simulated stacks, and a line on what it kept."""
    from latentz.calibration import calibrate

    cal = calibrate(
        list(stacks.stacks),
        stacks.z_nm,
        camera=camera,
        field_model=size.field_model,
        stage_offsets_px=stacks.origins[:, ::-1],
        roi_size=ROI_PX,
        progress=progress,
    )
    log.append(
        f"calibration: {len(cal.kept)} of {len(cal.culled)} particles kept, tilt "
        f"{cal.tilt_mrad:.2f} mrad (true {stacks.tilt_mrad:.2f})"
    )
    return cal


def _gear(scope: _Microscope, size: DemoSize, seed: int) -> tuple[GearMovie, np.ndarray]:
    """The gear movie's motion cycles, and a static segment (for drift) of its first frame."""
    from latentz import simulate as sim

    gear = sim.gear_movie(
        n_cycles=size.gear_cycles,
        n_particles=size.gear_particles,
        gear_diameter_um=size.gear_diameter_um,
        optics=scope.optics,
        aberrations=scope.aberrations,
        camera=scope.nominal,
        seed=seed,
    )
    static_truth = gear.truth[gear.truth["frame"] == 0]
    static_frames, _ = sim.render_spots(
        pd.concat([static_truth.assign(frame=f) for f in range(size.static_frames)])[
            ["frame", "x", "y", "z_nm", "photons", "diameter_nm"]
        ],
        frame_shape=gear.frames.shape[1:],
        origin=gear.origin,
        optics=scope.optics,
        aberrations=scope.aberrations,
        camera=scope.nominal,
        seed=seed + 1,
    )
    return gear, static_frames


def _localize_3d(
    frames: np.ndarray,
    cal: Calibration,
    camera: Camera,
    origin: tuple[int, int],
    progress: bool,
) -> pd.DataFrame:
    """The good 3D localizations of ``frames`` (cut at ``origin`` (row, column) from the
    field), with x, y in the frames' pixels."""
    from latentz.localization import localize
    from latentz.localization.quality import assess

    r0, c0 = origin
    found = localize(frames, camera=camera, roi_size=ROI_PX, progress=progress)
    # noise detections: widths far (2×) outside those the calibration saw
    low, high = cal.width_range_px
    widths = found[["wx", "wy"]]
    plausible = ((widths >= low / 2) & (widths <= 2 * high)).all(axis=1)
    found = found[found["converged"] & ~found["close_pair"] & plausible]
    field_spots = found.assign(x=found["x"] + c0, y=found["y"] + r0)
    # the verdict `localize(calibration=cal)` gives: widths and ρ off the calibration's
    # curves (a bead cut by the frame's edge, two overlapping) are not `good`
    located = assess(cal.apply(field_spots), cal)
    good = located["good"].to_numpy()
    return located[good].assign(x=found["x"].to_numpy()[good], y=found["y"].to_numpy()[good])


def _localization_errors(
    locs: pd.DataFrame,
    gear: GearMovie,
    stacks: CalibrationDataset,
    pixel_nm: float,
    log: list[str],
) -> pd.DataFrame:
    """The gear localizations' errors against truth (:func:`_errors`), and a line on their
    RMS with and without the correction and the magnification error."""
    pairs = _match_truth(locs, gear.truth)
    errors = _errors(pairs, pixel_nm, gear.centre_px, focal_plane(stacks.truth))
    in_range = float(locs["in_range"].mean())
    scaled, raw_scaled = _rms_after_scale(errors), _rms_after_scale(errors, "raw_")
    rms = rmse(errors)
    log.append(
        f"gear localizations: {len(locs)} ({100 * in_range:.1f} % in range); RMS error after "
        f"one offset: x {rms['rmse_x_nm']:.1f}, y {rms['rmse_y_nm']:.1f}, z {rms['rmse_z_nm']:.1f} "
        f"nm (uncorrected x {rms['raw_rmse_x_nm']:.1f}, y {rms['raw_rmse_y_nm']:.1f} nm); after "
        f"also removing the magnification error: x {scaled[0]:.1f}, y {scaled[1]:.1f} nm "
        f"(uncorrected x {raw_scaled[0]:.1f}, y {raw_scaled[1]:.1f} nm)"
    )
    return errors


def _motion(
    locs: pd.DataFrame,
    static: pd.DataFrame,
    gear: GearMovie,
    size: DemoSize,
    seed: int,
    out: Path,
    log: list[str],
) -> tuple[dict[str, pd.DataFrame], pd.DataFrame]:
    """Six degrees of freedom (the static segment after the cycles measures drift), written
    beside ``out``; and each against truth (:func:`_motion_against_truth`)."""
    from latentz.cli.steps import motion_outputs, track_tables
    from latentz.io import write_table

    static = static.assign(frame=static["frame"] + int(locs["frame"].max()) + 1)
    both = pd.concat([locs, static], ignore_index=True)
    static_ids = sorted(static["frame"].unique())
    tables = track_tables(both, n_sim=size.n_sim, seed=seed, static_frames=static_ids)
    paths = motion_outputs(out / "motion.csv")
    write_table(tables["tracks"], paths["tracks"])
    write_table(tables["motion"], paths["motion"])
    write_table(tables["uncertainty"].reset_index(names="dof"), paths["uncertainty"])
    write_table(tables["table1"].reset_index(names="dof"), paths["table1"])
    within = _motion_against_truth(tables, gear, size, seed, log)
    write_table(within, out / "motion_vs_truth.csv")
    return tables, within


def _motion_against_truth(
    tables: dict[str, pd.DataFrame], gear: GearMovie, size: DemoSize, seed: int, log: list[str]
) -> pd.DataFrame:
    """Per degree of freedom: RMS error against the gear's true motion, the Monte Carlo σ,
    and the errors against each cycle's own σ; and a line summarising them."""
    from latentz.motion import motion_uncertainty

    tracks, motion, unc = tables["tracks"], tables["motion"], tables["uncertainty"]
    truth_motion = gear.motion_of(tracks)
    # each cycle against its own σ: localization errors differ from cycle to cycle
    cycle_sigma = motion_uncertainty(
        tracks, motion, n_sim=size.n_sim, seed=seed, per_transition=True
    )
    compare = motion.merge(truth_motion, on="frame", suffixes=("", "_true")).merge(
        cycle_sigma, on="frame", suffixes=("", "_sigma")
    )
    dofs = ["gamma", "beta", "alpha", "dx_nm", "dy_nm", "dz_nm"]
    error = {d: compare[d] - compare[f"{d}_true"] for d in dofs}
    z_score = {d: error[d] / compare[f"{d}_sigma"] for d in dofs}
    within = pd.DataFrame(
        {
            "dof": dofs,
            "rms_error": [_rms(error[d]) for d in dofs],
            "sigma": [float(unc.loc[d, "sigma"]) for d in dofs],
            "std": [float(unc.loc[d, "std"]) for d in dofs],
            "rms_error_over_cycle_sigma": [_rms(z_score[d]) for d in dofs],
            "fraction_within_1_sigma": [float(np.mean(np.abs(z_score[d]) <= 1)) for d in dofs],
        }
    )
    log.append(
        f"motion: {len(motion)} transitions, {tracks['particle'].nunique()} tracks; gamma "
        f"{compare['gamma'].mean() * 1e3:.3f} mrad per cycle (true "
        f"{compare['gamma_true'].mean() * 1e3:.3f}); RMS of error against truth / the "
        "cycle's sigma (within 1 sigma): "
        + ", ".join(
            f"{DOF_NAMES[row.dof]} {row.rms_error_over_cycle_sigma:.2f} "
            f"({100 * row.fraction_within_1_sigma:.0f} %)"
            for row in within.itertuples()
        )
    )
    return within


def _calibration_quality(cal: Calibration, errors: pd.DataFrame) -> Section | None:
    """The calibration's quality section, with the gear particles' errors against truth."""
    from latentz.report import sections

    return sections.quality_section(
        cal,
        name="simulated calibration stacks",
        truth={
            "gear particles against simulated truth": errors,
            "the same, magnification error removed": _scale_removed(errors).drop(
                columns=["err_z_nm", "z_err_nm"]
            ),
        },
    )


def _psf_section(scope: _Microscope) -> Section:
    """The simulated microscope's PSFs through focus across the field."""
    from latentz import simulate as sim

    gallery = sim.psf_gallery(optics=scope.optics, aberrations=scope.aberrations)
    return Section(
        "Simulated microscope",
        "Pupil-function PSFs through focus at several field positions.",
        figures={"PSF gallery": figure_png(gallery)},
        captions={
            "PSF gallery": "One row per field position: an x–z section through the PSF "
            "(left) and x–y images at five defocus values. The shape changes with z "
            "(astigmatism) and with the field position: what the calibration learns."
        },
    )


def _calibration_sections(cal: Calibration, aperture_cal: Calibration) -> list[Section | None]:
    """The calibration, its field dependence, and the particles against the apertures."""
    from latentz.report import sections

    return [
        sections.calibration_section(cal, name="simulated calibration stacks"),
        sections.widefield_section(cal, name="simulated calibration stacks"),
        sections.emitter_arrays_section({"calibration particles": cal, "apertures": aperture_cal}),
    ]


def _localization_sections(locs: pd.DataFrame, errors: pd.DataFrame) -> list[Section | None]:
    """The gear's localizations, and their errors against truth."""
    from latentz.report import sections

    return [
        sections.localization_section(locs, name="simulated gear movie"),
        Section(
            "Localization against truth: simulated gear movie",
            "Gear particles: errors of the corrected positions (x' − Δx', y' − Δy', z) and of the "
            "apparent positions (x', y', no correction) against the simulated truth, after one "
            "global offset per axis. The corrected positions are where each particle appears at "
            "its own best focus (the paper's definition of its position); they differ from the "
            "simulated geometric positions by an in-focus shift that grows nearly linearly "
            "across the field, like a magnification error. So before that scale is removed the "
            "corrected lateral RMS can exceed the apparent; after it, the correction wins (see "
            "the Summary).",
            figures={
                "Errors against truth": figure_png(
                    error_figure(
                        errors,
                        title="Gear particles: error against truth "
                        "(one global offset removed per axis)",
                    )
                )
            },
        ),
    ]


def _motion_sections(tables: dict[str, pd.DataFrame], within: pd.DataFrame) -> list[Section | None]:
    """The gear's motion, the readout timing, and the motion against truth."""
    from latentz.report import sections

    return [
        sections.motion_section(
            tables["tracks"],
            tables["motion"],
            tables["uncertainty"],
            tables["table1"],
            name="simulated gear",
        ),
        sections.readout_section(),
        Section(
            "Motion against truth: simulated gear",
            "Each degree of freedom of every transition against the simulated truth, expressed "
            "about the same centre of rotation (the mean of all tracked positions). σ: the "
            "half-width of the Monte Carlo's 68 % interval over all cycles; standard deviation: "
            "its RMS over all cycles, larger where a few cycles are much noisier than the rest. "
            "Each cycle is also compared with its own Monte Carlo standard deviation (the "
            "cycle's σ): the RMS of error / cycle's σ should be near 1, and 68 % of the cycles "
            "should fall within their 1σ.",
            tables={"Per degree of freedom": _truth_table(within)},
        ),
    ]

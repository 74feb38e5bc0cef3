"""Report sections for each stage, shared by ``latentz report`` and ``latentz demo``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz._shared.figures import figure_png, image_png
from latentz.report import Section
from latentz.report.calibration_quality import quality_section

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = [
    "DOF_NAMES",
    "MOTION_DEFINITIONS",
    "quality_section",
    "calibration_section",
    "widefield_section",
    "emitter_arrays_section",
    "localization_section",
    "motion_section",
    "readout_section",
]


def _named(title: str, name: str) -> str:
    return f"{title}: {name}" if name else title


def calibration_section(
    cal: Calibration, *, particle: int | None = None, name: str = ""
) -> Section:
    """Fig. 2 for one particle (default: the kept one nearest the field centre), Fig. 3, best
    focus / tilt / field curvature, and the culled particles with reasons; ``name`` (the file or
    run) goes in the title."""
    from latentz.calibration import figure2, figure3, figure_focus

    table = cal.particles
    if particle is None:
        kept = table[~table["culled"]]
        centre = kept[["x", "y"]].mean().to_numpy()
        particle = int(np.argmin(np.hypot(*(kept[["x", "y"]].to_numpy() - centre).T)))
        particle = int(kept.index[particle])
    shapes = tuple(dict.fromkeys(("rho", "rho_A", cal.shape)))
    fig2 = f"Fig. 2: local models of particle {particle}"
    culled = table[table["culled"]]
    return Section(
        _named("Calibration", name),
        f"{len(cal.kept)} of {len(table)} calibration particles kept"
        + ("" if len(culled) else " (none culled)")
        + f"; substrate tilt {cal.tilt_mrad:.3f} mrad removed; ROI {cal.roi_size} px. z is on the "
        "tilt-corrected axis: z = 0 is the calibration particles' plane of best focus. Shape "
        "parameter: "
        + (cal.shape_choice["reason"] if cal.shape_choice else f"shape={cal.shape!r}, as given")
        + ".",
        figures={
            fig2: figure_png(figure2(cal, particle, shapes=shapes)),
            "Fig. 3: σ_z across the field": figure_png(figure3(cal)),
            "Best focus, tilt and field curvature": figure_png(figure_focus(cal)),
        },
        captions={
            fig2: "One calibration particle through focus. (a) Its apparent position x', y' "
            "coloured by z, the white circle at its best focus z_f. (b, c) The apparent lateral "
            "shifts Δx', Δy' from the position at z_f (points) and their polynomial models "
            "(green), with residuals and the local uncertainty σ below. (d) Amplitude A with its "
            "peak model; the red line marks z_f. Then each shape parameter against z with the "
            "inverse model z(shape) over its monotonic range (green), residuals and σ_z; the "
            f"calibration uses {cal.shape}.",
            "Fig. 3: σ_z across the field": "(a) z against the shape parameter for many "
            "particles; (b) map and (c) histogram of each particle's mean σ_z over the stated "
            "axial range; (d) mean and (e) 68 % spread of mean σ_z against the axial range for "
            "each shape parameter: lower is better.",
            "Best focus, tilt and field curvature": "(a) The piezo z of best focus of every "
            "particle (colour) with the fitted substrate tilt; (b) what remains after removing "
            "the plane: the field curvature. Crosses: culled particles.",
        },
        tables={
            "Culled particles": pd.DataFrame(
                {
                    "particle": culled["particle"].to_numpy(),
                    "x (µm)": culled["x_nm"].to_numpy() / 1e3,
                    "y (µm)": culled["y_nm"].to_numpy() / 1e3,
                    "reason": culled["reason"].str.replace(",", ", ").to_numpy(),
                }
            )
        }
        if len(culled)
        else {},
    )


def widefield_section(cal: Calibration, *, name: str = "") -> Section | None:
    """Widefield errors of each field model (Fig. 5) and the field maps (Fig. 4), if available."""
    from latentz.calibration.widefield import MIN_PARTICLES

    figures_of = getattr(cal, "evaluate_figures", None)
    if figures_of is None:
        return None
    if len(cal.kept) < MIN_PARTICLES:
        return Section(
            _named("Widefield calibration", name),
            f"Not shown: models across the field need at least {MIN_PARTICLES} kept calibration "
            f"particles, and this calibration has {len(cal.kept)}. Its models hold near "
            "those particles only.",
        )
    return Section(
        _named("Widefield calibration", name),
        "Errors of the field models (Zernike residuals, interpolants by leave-one-out) against z, "
        "and the field maps of apparent lateral motion and of z at a given shape value.",
        figures={name: figure_png(fig) for name, fig in figures_of().items()},
        captions=_WIDEFIELD_CAPTIONS,
    )


_WIDEFIELD_CAPTIONS = {
    "Fig. 5: widefield errors against z": "RMS error of each field model against z, for x, y "
    "and z, over the whole (square) field and the circle inscribed in it. Zernike: residuals of "
    "the fit; natural neighbour and nearest: each particle predicted from the others (leave one "
    "out). Lower is better; log scale.",
    "Supp. Figs. 11-14: error maps and histograms": "One row per field model. Left: each "
    "particle's RMS z error over z, where it sits in the field. Right: histograms of the x, y, "
    "z errors over all particles and z, square field (grey) and circle (blue), with the excess "
    "kurtosis (0 for a normal distribution).",
    "Fig. 4: field maps": "(a) Arrows: how far each calibration particle appears to move "
    "laterally between the two z in the title (the key gives the scale). (b) Each particle's "
    "z of best focus after tilt removal: the field curvature.",
}


def emitter_arrays_section(calibrations: dict) -> Section:
    """Supp. Fig. 9: where each emitter array (particles, apertures) shows ρ_A = 0 across the
    field: the shape of an image depends on the emitter as well as on the microscope."""
    from latentz.calibration import figure_shape_zero

    return Section(
        "Emitter arrays",
        "z at which each calibrated emitter's shape parameter is zero, for "
        f"{' and '.join(calibrations)}, with a Zernike model of each (Supp. Fig. 9).",
        figures={
            "Supp. Fig. 9: shape parameter zero across the field": figure_png(
                figure_shape_zero(calibrations)
            )
        },
    )


def _pixel_nm(locs: pd.DataFrame, finest: float, side_px: int) -> float:
    """The finest of 1, 2, 5 x 10^k nm (at least ``finest``) that fits the localizations' field
    in ``side_px`` pixels."""
    span = max(np.ptp(locs["x_nm"]), np.ptp(locs["y_nm"]), 1.0)
    for power in range(0, 6):
        for step in (1, 2, 5):
            pixel = step * 10.0**power
            if pixel >= finest and span / pixel <= side_px:
                return pixel
    return 1e5


def _seen(locs: pd.DataFrame) -> tuple[dict[str, bytes], dict[str, str], str]:
    """The super-resolution picture and the FRC curve of good, in-range localizations, their
    captions, and a sentence with the resolution (or why there is none)."""
    from latentz.analysis import frc, render

    usable = locs[np.isfinite(locs[["x_nm", "y_nm", "z_nm"]]).all(axis=1)]
    if usable.empty:
        return {}, {}, "No localization has a position in x, y and z to draw."
    pixel = _pixel_nm(usable, 10.0, 900)
    picture = f"Super-resolution image ({pixel:g} nm pixels)"
    figures = {picture: image_png(render(usable, pixel_nm=pixel))}
    captions = {
        picture: "Top: the x–y view, each localization a Gaussian of its reported x, y error; "
        "brightness is the density (saturating at the brightest 0.5 %), colour is z (bar at "
        "the right). Bottom: the x–z side view on the same x axis, z up, blurred by the "
        "reported x and z errors. The bar at the lower left of the x–y view gives the scale."
    }
    if len(usable) < 100:
        return figures, captions, "Too few localizations (fewer than 100) for an FRC."
    result = frc(usable, pixel_nm=_pixel_nm(usable, 5.0, 4096))
    figures["Fourier ring correlation"] = figure_png(result.figure())
    captions["Fourier ring correlation"] = (
        "Correlation of two halves of the data (alternate blocks of frames, 20 in all) ring by "
        "ring in Fourier space; the resolution is 1 / the frequency where it falls below 1/7. "
        "Emitters seen in both halves make it optimistic; drift makes it pessimistic."
    )
    said = (
        f"FRC resolution {result.resolution_nm:.1f} nm."
        if np.isfinite(result.resolution_nm)
        else "The FRC curve does not fall below 1/7: the resolution is finer than its pixels."
    )
    return figures, captions, said


def localization_section(locs: pd.DataFrame, *, name: str = "") -> Section:
    """Counts, the fraction in range, histograms of z and of the uncertainties, the
    super-resolution image and the FRC resolution, over the good rows
    (:func:`latentz.localization.quality.good_rows`; all in-range rows of older tables)."""
    import matplotlib.pyplot as plt

    from latentz.localization.quality import good_rows

    used, dropped = good_rows(locs)
    ok = used[used["in_range"].astype(bool)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.4))
    axes[0].hist(ok["z_nm"], bins=60)
    axes[0].set(xlabel="z (nm)", ylabel="localizations")
    for ax, col in zip(axes[1:], ("x_err_nm", "z_err_nm"), strict=True):
        ax.hist(ok[col].clip(upper=ok[col].quantile(0.99)), bins=60)
        ax.set(
            xlabel=f"reported {col.replace('_err_nm', '')} uncertainty (nm)",
            ylabel="localizations",
        )
    fig.tight_layout()
    summary = pd.DataFrame(
        {
            "localizations": [len(locs)],
            "good, in range": [len(ok)],
            "frames": [locs["frame"].nunique()],
            "median reported σ_x (nm)": [ok["x_err_nm"].median()],
            "median reported σ_y (nm)": [ok["y_err_nm"].median()],
            "median reported σ_z (nm)": [ok["z_err_nm"].median()],
        }
    )
    pictures, picture_captions, resolution = _seen(ok)
    return Section(
        _named("Localizations", name),
        "Spots outside the calibrated range of the shape parameter get no z (never "
        "extrapolated). The σ here are the uncertainties latentz reports; how well they describe "
        "the actual errors is in the calibration quality section at the top. "
        + (dropped[0].upper() + dropped[1:] + ". " if dropped else "")
        + resolution,
        figures={**pictures, "z and reported uncertainties": figure_png(fig)},
        captions={
            **picture_captions,
            "z and reported uncertainties": "Histograms over the good, in-range localizations "
            "of z and of the reported x and z uncertainties (the top 1 % clipped).",
        },
        tables={"Summary": summary},
    )


MOTION_DEFINITIONS = (
    "Definitions. Positions are centred on the centre of rotation, the mean of all tracked "
    "positions over all frames, and each transition between consecutive frames (one motion "
    "cycle) is the rigid motion p_i = R_i p_(i−1) + Δ_i that fits the particles best. γ is the "
    "angle of the rotation R_i about its axis; β (nutation) is the angle of that axis from the "
    "optical axis z; α (precession) is the azimuth of the axis in the x–y plane, from +x toward "
    "+y, undefined when the axis lies along z. Δx, Δy, Δz are the components of Δ_i: the "
    "translation of the centre of rotation. Angles are in mrad in the tables and figures."
)

_MOTION_CAPTIONS = {
    "motion": (
        "Fig. 8: six degrees of freedom per cycle",
        "Each point is one transition between consecutive frames; beside each series, its "
        "histogram. σ in each title is the Monte Carlo standard deviation from localization "
        "noise.",
    ),
    "residuals": (
        "Supp. Fig. 15: residuals of the rigid fits",
        "RMS over the particles of p_i − (R_i p_(i−1) + Δ_i) in each cycle, per axis: zero for a "
        "rigid body measured without error; larger values mean noise or non-rigid motion.",
    ),
    "centroid": (
        "Fig. 6d: centroid trajectory",
        "Mean position of the tracked particles in each frame, coloured by the nominal "
        "orientation (the accumulated rotation in steps of 2π / 64).",
    ),
    "play": (
        "Fig. 7: play at each orientation",
        "For each nominal orientation (the polar angle), the radial and axial range of the "
        "centroid over the frames that revisit it: the mechanical play.",
    ),
    "flexure": (
        "Supp. Fig. 18: flexure",
        "(a) z residuals of a plane fitted to the particles of each frame; (b) how the rigid "
        "and planar residuals of each particle correlate; (c, d) amplitude spectra of the RMS z "
        "residual per cycle at low and high frequency. A peak marks a periodic non-rigid "
        "motion and is labelled with its period; a period as long as the record is not resolved.",
    ),
    "monte_carlo": (
        "Supp. Fig. 17: Monte Carlo uncertainty",
        "Top: residuals of the rigid fits to the measured positions (green) and to one "
        "synthetic data set (black), which should match. Bottom: the errors of each degree of "
        "freedom in that simulation; their standard deviation is the σ of Table 1.",
    ),
    "out_of_plane": (
        "Supp. Fig. 20: out-of-plane play",
        "Largest z range of each particle at any nominal orientation against its distance from "
        "the centre of rotation; the slope of the line is the rotational play out of the plane.",
    ),
}


def _in_mrad(table: pd.DataFrame) -> pd.DataFrame:
    """A per-DOF table (dof as a column) with the angles' numbers in mrad."""
    out = table.copy()
    angles = out["dof"].isin(["gamma", "beta", "alpha"])
    numbers = [c for c in out.columns if pd.api.types.is_float_dtype(out[c])]
    out.loc[angles, numbers] *= 1e3
    out.insert(1, "unit", np.where(angles, "mrad", "nm"))
    out["dof"] = out["dof"].map(DOF_NAMES)
    return out.loc[:, ~out.columns.duplicated()]


DOF_NAMES = {
    "gamma": "γ",
    "beta": "β",
    "alpha": "α",
    "dx_nm": "Δx",
    "dy_nm": "Δy",
    "dz_nm": "Δz",
}


def motion_section(tracks, motion, uncertainty, summary, *, name: str = "") -> Section:
    """Every motion analysis figure (Figs. 6–8, Supp. Figs. 15, 18–20), Table 1 and the
    definitions of the degrees of freedom."""
    from latentz.motion import motion_figures

    figures = motion_figures(tracks, motion, uncertainty)
    centre = motion.attrs.get("centre_nm")
    where = (
        " The centre of rotation is at ("
        + ", ".join(f"{v / 1e3:.2f}" for v in centre)
        + ") µm in the microscope's x, y, z."
        if centre is not None and len(centre) == 3
        else ""
    )
    table1 = _in_mrad(summary.drop(columns="unit", errors="ignore").reset_index(names="dof"))
    return Section(
        _named("Motion in six degrees of freedom", name),
        f"{len(motion)} transitions of {tracks['particle'].nunique()} tracked particles."
        + where
        + "\n\n"
        + MOTION_DEFINITIONS
        + "\n\nTable 1: the mean and total range (maximum − minimum) of each degree of "
        "freedom and its uncertainty: localization (Monte Carlo, Supp. Note 2), drift (the RMS "
        "shift of the centroid between consecutive frames of a static segment, added in "
        "quadrature to the translations only, since a common shift does not rotate anything) and "
        "their total. A dash: not applicable, or no static segment was recorded.",
        figures={_MOTION_CAPTIONS[k][0]: figure_png(v) for k, v in figures.items()},
        captions={_MOTION_CAPTIONS[k][0]: _MOTION_CAPTIONS[k][1] for k in figures},
        tables={
            "Table 1": table1,
            "Monte Carlo uncertainty": _in_mrad(uncertainty.reset_index(names="dof")),
        },
    )


def readout_section(*, exposure_ms: float = 1.0, n_rows: int = 2048) -> Section:
    """Supp. Fig. 22: imaging frequency and centroid precision against exposure and readout."""
    from latentz.camera.readout import frame_rate_hz, readout_figure

    rate = frame_rate_hz(exposure_ms, n_rows)
    return Section(
        "Imaging frequency and readout extent",
        f"A global shutter at {exposure_ms:g} ms exposure reading {n_rows} rows images at "
        f"{rate:.1f} Hz. Fewer rows image faster but collect fewer signal photons for a rigid "
        "transformation (uniform field, illustrative photon rate; Supp. Fig. 22).",
        figures={
            "Supp. Fig. 22: readout extent against precision": figure_png(
                readout_figure(used=(exposure_ms, n_rows))
            )
        },
    )

"""Report sections for each stage, shared by ``latentz report`` and ``latentz demo``."""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentz.report import Section, figure_png

__all__ = [
    "calibration_section",
    "widefield_section",
    "emitter_arrays_section",
    "localization_section",
    "motion_section",
    "readout_section",
]


def calibration_section(cal, *, particle: int | None = None) -> Section:
    """Fig. 2 for one particle (default: the kept one nearest focus at the field centre),
    Fig. 3, best focus / tilt / field curvature, and the culled particles with reasons."""
    from latentz.calibration import figure2, figure3, figure_focus

    table = cal.particles
    if particle is None:
        kept = table[~table["culled"]]
        centre = kept[["x", "y"]].mean().to_numpy()
        particle = int(np.argmin(np.hypot(*(kept[["x", "y"]].to_numpy() - centre).T)))
        particle = int(kept.index[particle])
    return Section(
        "Calibration",
        f"{len(cal.kept)} of {len(table)} calibration particles kept; substrate tilt "
        f"{cal.tilt_mrad:.3f} mrad removed; ROI {cal.roi_size} px. Shape parameter: "
        + (cal.shape_choice["reason"] if cal.shape_choice else f"shape={cal.shape!r}, as given")
        + ".",
        figures={
            f"Fig. 2: local models of particle {particle}": figure_png(figure2(cal, particle)),
            "Fig. 3: sigma_z across the field": figure_png(figure3(cal)),
            "Best focus, tilt and field curvature": figure_png(figure_focus(cal)),
        },
        tables={"Culled particles": table[table["culled"]][["x", "y", "reason"]]},
    )


def widefield_section(cal) -> Section | None:
    """Widefield errors of each field model (Fig. 5) and the field maps (Fig. 4), if available."""
    figures_of = getattr(cal, "evaluate_figures", None)
    if figures_of is None:
        return None
    return Section(
        "Widefield calibration",
        "Errors of the field models (Zernike residuals, interpolants by leave-one-out) against z, "
        "and the field maps of apparent lateral motion and of z at a given shape value.",
        figures={name: figure_png(fig) for name, fig in figures_of().items()},
    )


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


def localization_section(locs: pd.DataFrame) -> Section:
    """Counts, the fraction in range, and histograms of z and of the uncertainties, over the
    good rows (:func:`latentz.quality.good_rows`; all in-range rows of older tables)."""
    import matplotlib.pyplot as plt

    from latentz.quality import good_rows

    used, dropped = good_rows(locs)
    ok = used[used["in_range"].astype(bool)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.4))
    axes[0].hist(ok["z_nm"], bins=60)
    axes[0].set(xlabel="z (nm)", ylabel="localizations")
    for ax, col in zip(axes[1:], ("x_err_nm", "z_err_nm"), strict=True):
        ax.hist(ok[col].clip(upper=ok[col].quantile(0.99)), bins=60)
        ax.set(xlabel=f"{col.replace('_err_nm', '')} uncertainty (nm)")
    fig.tight_layout()
    summary = pd.DataFrame(
        {
            "localizations": [len(locs)],
            "good, in range": [len(ok)],
            "frames": [locs["frame"].nunique()],
            "median x_err_nm": [ok["x_err_nm"].median()],
            "median y_err_nm": [ok["y_err_nm"].median()],
            "median z_err_nm": [ok["z_err_nm"].median()],
        }
    )
    return Section(
        "Localizations",
        "Spots outside the calibrated range of the shape parameter get no z (never extrapolated). "
        + (dropped[0].upper() + dropped[1:] + "." if dropped else ""),
        figures={"z and uncertainties": figure_png(fig)},
        tables={"Summary": summary},
    )


def motion_section(tracks, motion, uncertainty, summary) -> Section:
    """Every motion analysis figure (Figs. 6–8, Supp. Figs. 15, 18–20) and Table 1."""
    from latentz.motion import motion_figures

    return Section(
        "Motion in six degrees of freedom",
        f"{len(motion)} transitions of {tracks['particle'].nunique()} tracked particles. Table 1: "
        "mean, total range and uncertainty components (localization by Monte Carlo, drift, total).",
        figures={k: figure_png(v) for k, v in motion_figures(tracks, motion, uncertainty).items()},
        tables={
            "Table 1": summary.reset_index(names="dof"),
            "Monte Carlo uncertainty": uncertainty.reset_index(names="dof"),
        },
    )


def readout_section(*, exposure_ms: float = 1.0, n_rows: int = 2048) -> Section:
    """Supp. Fig. 22: imaging frequency and centroid precision against exposure and readout."""
    from latentz.readout import frame_rate_hz, readout_figure

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

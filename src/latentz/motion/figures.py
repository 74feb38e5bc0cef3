"""Figures of the motion analyses (paper Figs. 6–8, Supp. Figs. 15, 17, 18, 20).

Every function takes tables from :mod:`latentz.motion` and returns a matplotlib ``Figure`` built
without pyplot (no global state, safe off the main thread); :func:`save_figure` writes a PNG
atomically. Angles are plotted in mrad.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from latentz._shared.figures import mark_empty, save_figure
from latentz.motion import analyses
from latentz.motion.analyses import OutOfPlanePlay
from latentz.motion.uncertainty import representative_simulation

__all__ = [
    "motion_figures",
    "save_figure",
    "figure_motion",
    "figure_residuals",
    "figure_centroid",
    "figure_play",
    "figure_flexure",
    "figure_out_of_plane_play",
    "figure_monte_carlo",
]

DOF_ORDER = ("dx_nm", "dy_nm", "dz_nm", "gamma", "beta", "alpha")  # Supp. Fig. 17 (e-j)

_LABELS = {
    "gamma": ("γ", "mrad", 1e3),
    "beta": ("β", "mrad", 1e3),
    "alpha": ("α", "mrad", 1e3),
    "dx_nm": ("Δx", "nm", 1.0),
    "dy_nm": ("Δy", "nm", 1.0),
    "dz_nm": ("Δz", "nm", 1.0),
}


def _series_with_histogram(fig, gs, row, col, x, y, label, sigma=None):
    ax = fig.add_subplot(gs[row, 2 * col])
    hist = fig.add_subplot(gs[row, 2 * col + 1], sharey=ax)
    ax.plot(x, y, ".", ms=2 if len(x) > 100 else 5, color="tab:blue")
    hist.set_xlabel("count")
    finite = y[np.isfinite(y)]
    if finite.size:
        hist.hist(finite, bins=40, orientation="horizontal", color="tab:blue")
    if sigma is not None:
        ax.set_title(f"{label}   (σ = {sigma:.3g})", fontsize=9)
    else:
        ax.set_title(label, fontsize=9)
    hist.tick_params(labelleft=False)
    ax.set_xlabel("motion cycle")
    return ax


def figure_motion(motion: pd.DataFrame, uncertainty: pd.DataFrame | None = None) -> Figure:
    """Six degrees of freedom per motion cycle with histograms (Fig. 8a–c, e–g)."""
    fig = Figure(figsize=(12, 6.5), layout="constrained")
    gs = fig.add_gridspec(2, 6, width_ratios=[4, 1] * 3)
    for k, dof in enumerate(_LABELS):
        name, unit, scale = _LABELS[dof]
        sigma = None
        if uncertainty is not None and dof in uncertainty.index:
            sigma = float(uncertainty.loc[dof, "sigma"]) * scale
        ax = _series_with_histogram(
            fig,
            gs,
            k // 3,
            k % 3,
            motion["frame"].to_numpy(),
            motion[dof].to_numpy() * scale,
            f"{name} ({unit})",
            sigma,
        )
        ax.set_ylabel(f"{name} ({unit})")
    return fig


def figure_residuals(motion: pd.DataFrame) -> Figure:
    """RMS residuals of the rigid transforms in x, y and z per cycle (Supp. Fig. 15)."""
    fig = Figure(figsize=(12, 3.6), layout="constrained")
    gs = fig.add_gridspec(1, 6, width_ratios=[4, 1] * 3)
    for k, axis in enumerate("xyz"):
        column = f"rms_{axis}_nm"
        values = motion[column].to_numpy()
        ax = _series_with_histogram(
            fig,
            gs,
            0,
            k,
            motion["frame"].to_numpy(),
            values,
            f"RMS residual {axis} (nm), mean {np.nanmean(values):.3g}",
        )
        ax.set_ylabel(f"{axis} residual (nm)")
    return fig


def figure_centroid(centroids: pd.DataFrame) -> Figure:
    """3D centroid trajectory coloured by nominal orientation (Fig. 6d)."""
    fig = Figure(figsize=(6.5, 5.5), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    art = ax.scatter(
        centroids["x_nm"] / 1e3,
        centroids["y_nm"] / 1e3,
        centroids["z_nm"],
        c=centroids["nominal"],
        cmap="twilight",
        s=4,
    )
    ax.set_xlabel("x (µm)", labelpad=12)
    ax.set_ylabel("y (µm)", labelpad=12)
    ax.set_zlabel("z (nm)", labelpad=12)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):  # few ticks, so none overlap
        axis.set_major_locator(MaxNLocator(4))
    fig.colorbar(art, ax=ax, shrink=0.6, label="nominal orientation")
    return fig


def figure_play(ranges: pd.DataFrame) -> Figure:
    """Radial and axial range of the centroid at each nominal orientation, polar (Fig. 7)."""
    fig = Figure(figsize=(10, 4.8), layout="constrained")
    width = 2 * np.pi / max(len(ranges), 1) * 0.8
    if not (ranges["n_visits"] >= 2).any():
        fig.set_size_inches(10, 1.4)
        mark_empty(
            fig.add_subplot(),
            "No nominal orientation was visited twice (the record is shorter than one "
            "revolution),\nso the play, the range of the centroid over revisits, "
            "cannot be measured.",
        )
        return fig
    for k, (column, title) in enumerate(
        [("radial_range_nm", "radial range (nm)"), ("axial_range_nm", "axial range (nm)")]
    ):
        ax = fig.add_subplot(1, 2, k + 1, projection="polar")
        ax.bar(ranges["theta"], ranges[column], width=width, color=f"C{k}", alpha=0.8)
        ax.set_title(title, fontsize=10)
    return fig


def figure_flexure(
    planar: pd.DataFrame,
    correlation: pd.DataFrame,
    rigid_spectrum: pd.DataFrame,
    planar_spectrum: pd.DataFrame,
    *,
    pair: tuple[np.ndarray, np.ndarray] | None = None,
) -> Figure:
    """Planar-fit residuals, their correlation with rigid residuals, and the spectra of the RMS
    residual series (Supp. Fig. 18). ``pair`` optionally gives (planar, rigid) residuals of one
    particle for the scatter plot; otherwise the per-particle correlations are shown."""
    fig = Figure(figsize=(12, 7), layout="constrained")
    ax = fig.add_subplot(2, 2, 1)
    ax.plot(planar["frame"], planar["res_z_nm"], ".", ms=1 if len(planar) > 1000 else 3, alpha=0.5)
    ax.set_xlabel("motion cycle")
    ax.set_ylabel("planar residual z (nm)")
    ax.set_title("(a) z residuals of a plane fitted to each frame", fontsize=10)
    ax = fig.add_subplot(2, 2, 2)
    if pair is not None:
        x, y = pair
        ax.plot(x, y, ".", ms=2)
        ok = np.isfinite(x) & np.isfinite(y)
        slope, intercept = np.polyfit(x[ok], y[ok], 1)
        grid = np.linspace(np.nanmin(x), np.nanmax(x), 2)
        ax.plot(grid, intercept + slope * grid, color="0.4")
        ax.set_xlabel("planar residual z (nm)")
        ax.set_ylabel("rigid residual z (nm)")
    else:
        # particles by position along the axis; at most ~20 tick labels so none overlap
        index = np.arange(len(correlation))
        ax.bar(index, correlation["correlation"])
        ticks = index[:: max(1, int(np.ceil(len(index) / 20)))]
        ax.set_xticks(ticks, correlation["particle"].astype(str).to_numpy()[ticks], fontsize=7)
        ax.set_xlabel("particle (track id)")
        ax.set_ylabel("correlation, rigid vs planar z residuals")
    r = correlation["correlation"]
    ax.set_title(f"(b) mean correlation {r.mean():.2f} ± {r.std():.2f}", fontsize=10)
    # a peak is a period only if the record holds at least two of them
    record = float(planar["frame"].max() - planar["frame"].min() + 1) if len(planar) else 0.0
    for k, (lo, hi) in enumerate([(0.0, 0.05), (0.05, 0.5)]):
        ax = fig.add_subplot(2, 2, 3 + k)
        for spectrum, label, color in (
            (planar_spectrum, "planar", "black"),
            (rigid_spectrum, "rigid", "tab:purple"),
        ):
            sel = (spectrum["frequency"] >= lo) & (spectrum["frequency"] <= hi)
            if not sel.any():
                continue
            resolved = sel & (spectrum["period_cycles"] <= record / 2)
            peak = spectrum.loc[resolved].nlargest(1, "amplitude")
            key = label
            if len(peak):
                key += f": peak at {float(peak['period_cycles'].iloc[0]):.1f} cycles"
                ax.plot(peak["frequency"], peak["amplitude"], "v", color=color, ms=6)
            ax.plot(
                spectrum.loc[sel, "frequency"],
                spectrum.loc[sel, "amplitude"],
                color=color,
                lw=0.8,
                label=key,
            )
        ax.set_title(f"({'cd'[k]}) spectrum, {lo:g}–{hi:g} per cycle", fontsize=10)
        ax.set_xlabel("frequency (per motion cycle)")
        ax.set_ylabel("amplitude of RMS z residual (nm)")
        if ax.get_lines():
            ax.legend(fontsize=8, title=f"periods up to {record / 2:.0f} cycles", title_fontsize=8)
        else:
            mark_empty(ax, f"the record ({record:.0f} cycles) is too short\nfor these frequencies")
    return fig


def figure_out_of_plane_play(result: OutOfPlanePlay, *, z_err_nm: float | None = None) -> Figure:
    """Largest z range of each particle against its distance from the centre (Supp. Fig. 20)."""
    fig = Figure(figsize=(6, 4.5), layout="constrained")
    ax = fig.add_subplot()
    table = result.particles
    ax.errorbar(
        table["distance_nm"] / 1e3,
        table["max_z_range_nm"],
        yerr=z_err_nm,
        fmt="o",
        ms=4,
        capsize=2,
    )
    grid = np.linspace(table["distance_nm"].min(), table["distance_nm"].max(), 2)  # data only
    ax.plot(grid / 1e3, result.intercept_nm + result.slope_rad * grid, color="k")
    ax.set_xlabel("distance from centre of rotation (µm)")
    ax.set_ylabel("maximum z range (nm)")
    ax.set_title(
        f"slope {result.slope_rad * 1e3:.2f} ± {result.slope_err_rad * 1e3:.2f} mrad", fontsize=10
    )
    return fig


def figure_monte_carlo(simulation: dict[str, pd.DataFrame]) -> Figure:
    """Supp. Fig. 17 (b–j): residuals of the rigid fits to the experimental and the synthetic
    positions in x, y, z, and the errors of each degree of freedom in one simulation
    (:func:`latentz.motion.uncertainty.representative_simulation`)."""
    fig = Figure(figsize=(15, 6.5))
    gs = fig.add_gridspec(2, 6)
    residuals, errors = simulation["residuals"], simulation["errors"]
    for col, axis in enumerate(("x_nm", "y_nm", "z_nm")):
        ax = fig.add_subplot(gs[0, 2 * col : 2 * col + 2])
        values = residuals[axis].to_numpy()
        bins = np.histogram_bin_edges(values[np.isfinite(values)], bins=40)
        for source, color in (("experimental", "tab:green"), ("synthetic", "k")):
            part = residuals.loc[residuals["source"] == source, axis].dropna()
            rms = float(np.sqrt(np.mean(part**2)))
            ax.hist(part, bins=bins, histtype="step", color=color, label=f"{source}, RMS {rms:.2f}")
        ax.set(xlabel=f"residual {axis[0]} (nm)", ylabel="count")
        ax.legend(fontsize=8)
    for col, dof in enumerate(DOF_ORDER):
        label, unit, factor = _LABELS[dof]
        ax = fig.add_subplot(gs[1, col])
        values = errors[dof].dropna().to_numpy() * factor
        ax.hist(values, bins=30, color="0.4")
        ax.set(xlabel=f"error of {label} ({unit})", title=f"SD {values.std():.3g} {unit}")
    fig.suptitle("Monte Carlo: residuals (experimental vs synthetic) and one simulation's errors")
    fig.tight_layout()
    return fig


def motion_figures(
    tracks: pd.DataFrame,
    motion: pd.DataFrame,
    uncertainty: pd.DataFrame | None = None,
    *,
    steps_per_rev: int = 64,
) -> dict[str, Figure]:
    """Run every analysis on linked ``tracks`` and their ``motion`` and return all figures.

    Keys: motion, residuals, centroid, play, flexure, monte_carlo, and out_of_plane (only when
    particles revisit nominal locations, i.e. more than one revolution).
    """
    centroids = analyses.centroid_trajectory(tracks, motion, steps_per_rev=steps_per_rev)
    planar = analyses.planar_residuals(tracks)
    rms = np.sqrt((planar["res_z_nm"] ** 2).groupby(planar["frame"]).mean())
    rigid_spectrum = analyses.residual_spectrum(
        motion["frame"].to_numpy(), motion["rms_z_nm"].to_numpy()
    )
    planar_spectrum = analyses.residual_spectrum(rms.index.to_numpy(), rms.to_numpy())
    figures = {
        "motion": figure_motion(motion, uncertainty),
        "residuals": figure_residuals(motion),
        "centroid": figure_centroid(centroids),
        "play": figure_play(analyses.play(centroids)),
        "flexure": figure_flexure(
            planar, analyses.residual_correlation(tracks), rigid_spectrum, planar_spectrum
        ),
        "monte_carlo": figure_monte_carlo(representative_simulation(tracks, motion)),
    }
    if len(motion) >= steps_per_rev + 1:
        result = analyses.out_of_plane_play(tracks, motion, steps_per_rev=steps_per_rev)
        figures["out_of_plane"] = figure_out_of_plane_play(
            result, z_err_nm=float(np.sqrt(np.nanmean(motion["rms_z_nm"] ** 2)))
        )
    return figures

"""Figures of the local calibration: the paper's Fig. 2 (one particle) and Fig. 3 (the field).

Both functions return a matplotlib Figure and, given ``path``, also write it as PNG atomically.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.ticker import MaxNLocator

from latentz._shared.figures import mark_empty, save_figure
from latentz._shared.validate import check_int
from latentz.calibration.result import PAPER_SHAPES, Calibration

__all__ = ["figure2", "figure3", "figure_focus", "figure_shape_zero"]

_LABELS = {
    "rho": "ρ",
    "rho_w": "ρ_w",
    "rho_A": "ρ_A",
    "auto": "e_θ (|w_x|+|w_y|)/2",
    "auto_A": "e_θ / A_n",
}
_MARKERS = {"rho": "^", "rho_w": "s", "rho_A": "o", "auto": "D", "auto_A": "v"}


def _save(fig: Any, path: str | os.PathLike | None) -> None:
    if path is not None:
        save_figure(fig, path)


def figure2(
    cal: Calibration,
    particle: int,
    *,
    shapes: tuple[str, ...] = ("rho", "rho_A"),
    path: str | os.PathLike | None = None,
) -> Any:
    """Fig. 2 for one calibration particle.

    Panels: (a) apparent position x', y' through focus coloured by z, with the position at z_f;
    (b, c) Δx'(z), Δy'(z) (nm) with their polynomial and σ_Δ; (d) A(z) with its order-5 peak
    model and z_f; (e, f, …) each shape parameter in ``shapes`` with its inverse model over the
    monotonic range and σ_z. Middle row: residuals; bottom row: σ(z) from the residuals.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = len(cal.particles)
    p = check_int("particle", particle, minimum=0)
    if p >= n:
        raise ValueError(f"Expected `particle` < {n} (number of calibration particles), got {p}.")
    cols = 3 + len(shapes)
    fig, axes = plt.subplots(
        3,
        cols + 1,
        figsize=(3.1 * (cols + 1), 7.5),
        height_ratios=[3, 1.2, 1.2],
        squeeze=False,
    )
    _position_panel(fig, axes[:, 0], cal, p)
    _shift_panels(axes[:, 1:3], cal, p)
    _amplitude_panel(axes[:, 3], cal, p)
    for col, shape in enumerate(shapes, start=4):
        _shape_panel(axes[:, col], cal, p, shape, letter=chr(ord("e") + col - 4))
    for col in range(1, cols + 1):
        axes[0, col].set_xlabel("z (nm)")
    for ax in axes[:, 1:].flat:  # a few z ticks, so that none overlap (not on worded panels)
        if not ax.texts:
            ax.xaxis.set_major_locator(MaxNLocator(4))
    fig.tight_layout()
    _save(fig, path)
    return fig


def _position_panel(fig: Any, column: np.ndarray, cal: Calibration, p: int) -> None:
    """(a): the apparent position x', y' (nm) through focus coloured by z, about the position
    at z_f; the column's lower axes left empty."""
    tr, px, z = cal.traces, cal.camera.pixel_size_nm, cal.local.z_nm[p]
    zf = cal.local.z_f[p]
    ax = column[0]
    x0, y0 = (m[p : p + 1](np.array([zf]))[0] for m in (_abs_model(cal, "x"), _abs_model(cal, "y")))
    # positions relative to the particle's position at z_f, so no axis needs an offset
    sc = ax.scatter((tr["x"][p] - x0) * px, (tr["y"][p] - y0) * px, c=z, s=10, cmap="viridis")
    ax.plot(0.0, 0.0, "o", mfc="white", mec="k", ms=8)
    ax.set(
        xlabel="x' − x'(z_f) (nm)",
        ylabel="y' − y'(z_f) (nm)",
        title=f"(a) particle {p} at ({x0 * px / 1e3:.1f}, {y0 * px / 1e3:.1f}) µm",
    )
    ax.set_aspect("equal", adjustable="datalim")
    bar = fig.colorbar(sc, ax=ax, location="bottom", pad=0.2)
    bar.set_label("z (nm)")
    for row in (1, 2):
        column[row].axis("off")


def _shift_panels(axes: np.ndarray, cal: Calibration, p: int) -> None:
    """(b, c): Δx'(z), Δy'(z) (nm) with their polynomial, residuals and σ_Δ, in the columns of
    ``axes`` (3, 2)."""
    local, tr, px = cal.local, cal.traces, cal.camera.pixel_size_nm
    z, zf = local.z_nm[p], local.z_f[p]
    zz = np.linspace(np.nanmin(z), np.nanmax(z), 400)
    panels = [
        ("(b) Δx'", "x", local.dx, local.sigma_dx[p] * px, "σ_Δx' (nm)"),
        ("(c) Δy'", "y", local.dy, local.sigma_dy[p] * px, "σ_Δy' (nm)"),
    ]
    for col, (title, axis, model, sigma, slabel) in enumerate(panels):
        data = (tr[axis][p] - _abs_model(cal, axis)[p : p + 1](np.array([zf]))[0]) * px
        curve = model[p : p + 1](zz[None])[0] * px
        top, mid, bottom = axes[:, col]
        top.plot(z, data, "k.", ms=3)
        # the model only over the z its data cover, on the data's scale
        seen = np.isfinite(data)
        span = (zz >= np.min(z[seen])) & (zz <= np.max(z[seen])) if seen.any() else zz < -np.inf
        top.plot(zz[span], curve[span], "g-", lw=1.5)
        _limit_to(top, data)
        top.set_title(title)
        top.set_ylabel(f"{title[4:]} (nm)")
        mid.plot(z, data - model[p : p + 1](z[None])[0] * px, "k.", ms=2)
        mid.set_ylabel("residual (nm)")
        bottom.plot(z, sigma, "b-")
        bottom.set(xlabel="z (nm)", ylabel=slabel)


def _amplitude_panel(column: np.ndarray, cal: Calibration, p: int) -> None:
    """(d): the peak amplitude A(z) with its peak model, z_f and residuals."""
    local = cal.local
    z, zf = local.z_nm[p], local.z_f[p]
    top, mid, bottom = column
    amp = cal.traces["amplitude"][p]
    top.plot(z, amp, "k.", ms=3)
    dom = local.amplitude.domain[p]
    za = np.linspace(dom[0], dom[1], 200)
    top.plot(za, local.amplitude[p : p + 1](za[None])[0], "g-", lw=1.5)
    top.axvline(zf, color="r", lw=1)
    top.set_title(f"(d) A, z_f = {zf:.0f} nm")
    top.set_ylabel("peak amplitude A (photoelectrons / px)")
    inside = (z >= dom[0]) & (z <= dom[1])
    mid.plot(z[inside], (amp - local.amplitude[p : p + 1](z[None])[0])[inside], "k.", ms=2)
    mid.set_ylabel("residual (e⁻ / px)")
    bottom.axis("off")


def _shape_panel(column: np.ndarray, cal: Calibration, p: int, shape: str, letter: str) -> None:
    """(e, f, …): a shape parameter through focus with its inverse model over the monotonic
    range, the z residuals and σ_z; a worded panel where it has no monotonic range."""
    z = cal.local.z_nm[p]
    top, mid, bottom = column
    model = cal.local.shapes[shape]
    values = model.values[p]
    top.plot(z, values, "k.", ms=3)
    lo, hi = model.inverse.domain[p]
    used = " — used" if shape == cal.shape else ""
    top.set_title(f"({letter}) {_LABELS[shape]}{used}")
    top.set_ylabel(f"{_LABELS[shape]} (dimensionless)")
    finite_sigma = np.isfinite(model.sigma_z[p])
    if not (model.inverse.valid[p] and finite_sigma.any()):
        reason = f"{_LABELS[shape]} has no monotonic range\nfor this particle: no z from it"
        mark_empty(mid, reason)
        mark_empty(bottom, "no σ_z: see above")
        return
    ss = np.linspace(lo, hi, 300)
    zs = model.inverse[p : p + 1](ss[None])[0]
    # the inverse model only where it maps into the z this particle was imaged over
    shown = (zs >= np.nanmin(z)) & (zs <= np.nanmax(z))
    top.plot(np.where(shown, zs, np.nan), ss, "g-", lw=1.5)
    _limit_to(top, values)
    res = z - model.inverse[p : p + 1](values[None])[0]
    mid.plot(z, np.where(finite_sigma, res, np.nan), "k.", ms=2)
    mid.set_ylabel("z residual (nm)")
    bottom.plot(z, model.sigma_z[p], "b-")
    bottom.set(xlabel="z (nm)", ylabel="σ_z (nm)")


def _limit_to(ax: Any, data: np.ndarray) -> None:
    """y limits that hold the data (with a margin), whatever a model drawn beside it does."""
    finite = np.asarray(data, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size:
        lo, hi = finite.min(), finite.max()
        margin = 0.08 * (hi - lo) or 1.0
        ax.set_ylim(lo - margin, hi + margin)


def _abs_model(cal: Calibration, axis: str):
    """x'(z) or y'(z) (pixels): Δ model plus the position at z_f."""
    from latentz.calibration.polymodel import PolyModel

    delta = cal.local.dx if axis == "x" else cal.local.dy
    data = cal.traces[axis]
    offset = np.nanmedian(data - delta(cal.local.z_nm), axis=1)
    return PolyModel(delta.coef, delta.domain).shifted(-offset)


def interpercentile(values: np.ndarray) -> float:
    """68 % interpercentile range (16th to 84th percentile) of the finite values."""
    finite = values[np.isfinite(values)]
    return float(np.subtract(*np.percentile(finite, [84, 16]))) if finite.size else np.nan


def figure3(
    cal: Calibration,
    *,
    shape: str | None = None,
    range_nm: float = 6000.0,
    ranges_nm: Any = None,
    path: str | os.PathLike | None = None,
) -> Any:
    """Fig. 3: z(shape) of many particles, the map and histogram of mean σ_z over ``range_nm``,
    and the mean and 68 % interpercentile range of mean σ_z against the axial range for ρ, ρ_w
    and ρ_A (and the chosen shape, if another). Culled particles are left out."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    shape = shape or cal.shape
    kept = ~cal.culled
    # the axial ranges this calibration can speak for: no wider than its particles' z span
    span = float(np.nanmedian(np.diff(cal.z_span_nm[kept], axis=1))) if kept.any() else 0.0
    range_nm = min(range_nm, np.floor(0.9 * span / 100.0) * 100.0) if span > 0 else range_nm
    if ranges_nm is None:
        step = 500.0 if span >= 2000 else 100.0
        ranges = np.arange(step * 2, max(range_nm, 2 * step) + 1, step)
    else:
        ranges = np.asarray(ranges_nm)
    sigma = cal.mean_sigma_z(shape, range_nm)
    fig, axes = plt.subplots(1, 5, figsize=(22, 4.2))
    ax = axes[0]
    model = cal.local.shapes[shape].inverse
    order = np.argsort(np.where(np.isfinite(sigma), sigma, np.inf))
    show = [i for i in order if kept[i] and model.valid[i]]
    for i in show[:: max(1, len(show) // 60)]:
        ss = np.linspace(*model.domain[i], 100)
        zs = model[i : i + 1](ss[None])[0]
        # each curve only where it maps into the z its particle was imaged over
        lo, hi = cal.z_span_nm[i]
        ax.plot(ss, np.where((zs >= lo) & (zs <= hi), zs, np.nan), lw=0.6, color="0.6")
    ax.set(xlabel=_LABELS.get(shape, shape), ylabel="z (nm)", title=f"(a) z({_LABELS[shape]})")
    if not show:
        mark_empty(ax, f"no kept particle has a monotonic\nrange of {_LABELS[shape]}")
    ax = axes[1]
    pos = cal.positions * cal.camera.pixel_size_nm / 1000
    have = kept & np.isfinite(sigma)
    title = f"mean σ_z over {range_nm / 1000:g} µm"
    if have.any():
        sc = ax.scatter(pos[have, 0], pos[have, 1], c=sigma[have], s=12, cmap="magma")
        ax.set(xlabel="x (µm)", ylabel="y (µm)", title=f"(b) {title}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.invert_yaxis()
        fig.colorbar(sc, ax=ax, label="σ_z (nm)")
        axes[2].hist(sigma[have], bins=30, color="0.4")
        axes[2].set(xlabel="mean σ_z (nm)", ylabel="particles", title=f"(c) n = {have.sum()}")
    else:
        empty = f"no kept particle has {_LABELS[shape]}\nmonotonic over {range_nm / 1000:g} µm"
        mark_empty(ax, f"(b) {title}:\n{empty}")
        mark_empty(axes[2], f"(c) histogram of {title}:\n{empty}")
    for name in dict.fromkeys((*PAPER_SHAPES, shape)):
        per_range = [cal.mean_sigma_z(name, r)[kept] for r in ranges]
        means = [np.nanmean(v) if np.isfinite(v).any() else np.nan for v in per_range]
        spread = [interpercentile(v) for v in per_range]
        axes[3].plot(ranges / 1000, means, marker=_MARKERS[name], label=_LABELS[name])
        axes[4].plot(ranges / 1000, spread, marker=_MARKERS[name], label=_LABELS[name])
    for ax, label, title in (
        (axes[3], "mean σ_z (nm)", "(d) mean σ_z"),
        (axes[4], "68 % range of σ_z (nm)", "(e) spread of σ_z"),
    ):
        ax.set(xlabel="axial range (µm)", ylabel=label, title=title)
        values = np.concatenate([line.get_ydata() for line in ax.get_lines()])
        if np.any(np.asarray(values, dtype=float) > 0):
            ax.set_yscale("log")
        else:
            mark_empty(ax, f"{title}: no particle has a\nmonotonic range over these ranges")
    if axes[3].get_lines():
        axes[3].legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)
    return fig


def figure_focus(cal: Calibration, *, path: str | os.PathLike | None = None) -> Any:
    """The surface of best focus before and after tilt removal (paper Methods, Supp. Fig. 3):
    (a) z_f (piezo) over the field with the tilt plane's nutation and azimuth, (b) the field
    curvature z_f − plane. Culled particles are drawn as crosses."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    table = cal.particles
    kept = ~table["culled"].to_numpy()
    pos = cal.positions * cal.camera.pixel_size_nm / 1000
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, column, title in (
        (
            axes[0],
            "z_f",
            f"(a) z_f, tilt {cal.tilt_mrad:.2f} mrad toward "
            f"{np.degrees(cal.plane.azimuth_rad):.0f}°",
        ),
        (axes[1], "z_f_nm", "(b) field curvature z_f − plane"),
    ):
        values = table[column].to_numpy()
        sc = ax.scatter(pos[kept, 0], pos[kept, 1], c=values[kept], s=14, cmap="coolwarm")
        ax.scatter(pos[~kept, 0], pos[~kept, 1], marker="x", c="k", s=14)
        ax.set(xlabel="x (µm)", ylabel="y (µm)", title=title)
        ax.set_aspect("equal", adjustable="datalim")
        ax.invert_yaxis()
        fig.colorbar(sc, ax=ax, label="nm")
    fig.tight_layout()
    _save(fig, path)
    return fig


def figure_shape_zero(
    calibrations: Mapping[str, Calibration],
    *,
    value: float = 0.0,
    max_terms: int = 45,
    path: str | os.PathLike | None = None,
) -> Any:
    """Supp. Fig. 9: where each emitter array shows one shape value, across the field.

    For each calibration (for example ``{"particles": cal, "apertures": cal_apertures}``): (top)
    the z at which each kept emitter's shape parameter equals ``value`` (its inverse model; z on
    that calibration's tilt-corrected axis), and (bottom) a Zernike model of those values (up to
    ``max_terms`` terms, chosen by leave-one-out) over the emitters' extent. The two arrays show
    different field dependences: the shape of an image depends on the emitter as well as on the
    microscope.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from latentz.calibration.fieldmodels import FieldModel

    n = len(calibrations)
    fig, axes = plt.subplots(2, n, figsize=(5.5 * n, 9.0), squeeze=False)
    for col, (name, cal) in enumerate(calibrations.items()):
        kept = cal.kept
        z = cal.local_z(value)[kept]
        x, y = cal.positions[kept].T
        ok = np.isfinite(z)
        px = cal.camera.pixel_size_nm / 1000
        label = _LABELS.get(cal.shape, cal.shape)
        ax = axes[0, col]
        sc = ax.scatter(x[ok] * px, y[ok] * px, c=z[ok], s=14, cmap="viridis")
        fig.colorbar(sc, ax=ax, label="z (nm)")
        ax.set(title=f"({'ab'[col % 2]}) {name}: z at {label} = {value:g}", ylabel="y (µm)")
        ax = axes[1, col]
        if ok.sum() >= 4:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                model = FieldModel.from_estimate(
                    x[ok],
                    y[ok],
                    z[ok],
                    kind="zernike",
                    field_shape=tuple(cal.options["field_shape"]),
                    n_terms=max_terms,
                )
            gx, gy = np.meshgrid(
                np.linspace(x[ok].min(), x[ok].max(), 80), np.linspace(y[ok].min(), y[ok].max(), 80)
            )
            surface = model(gx.ravel(), gy.ravel()).reshape(gx.shape)
            mesh = ax.pcolormesh(gx * px, gy * px, surface, cmap="viridis", shading="auto")
            fig.colorbar(mesh, ax=ax, label="z (nm)")
            terms = int(model.n_terms_effective[0])
            ax.set(title=f"({'cd'[col % 2]}) Zernike model, {terms} terms")
        ax.set(xlabel="x (µm)", ylabel="y (µm)")
        for ax in axes[:, col]:
            ax.set_aspect("equal", adjustable="datalim")
            ax.invert_yaxis()
    fig.tight_layout()
    _save(fig, path)
    return fig

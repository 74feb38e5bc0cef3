"""Errors of widefield calibration (paper Fig. 5, Supp. Figs. 11–14) and the field maps of Fig. 4.

For every field model, the local values of the calibration particles are modelled across the
field at each z (for Δx', Δy') and at each shape value (for z), and the errors are the Zernike
fit residuals or, for the interpolants, the leave-one-out residuals: the value predicted at a
particle from all the others. Their RMS against z, for the square field and a circular subset,
with the excess kurtosis of each error histogram, is the table :func:`evaluate` returns.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from latentz._shared.figures import mark_empty
from latentz.calibration.fieldmodels import FIELD_MODEL_KINDS as FIELD_MODELS
from latentz.calibration.fieldmodels import FieldModel, field_errors
from latentz.calibration.widefield import MIN_PARTICLES, covered_span

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["evaluate", "evaluate_figures", "crossval_report"]


def _columns(cal: CalibrationView, n_z: int, n_s: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per axis: (values (n_kept, m) in nm, the z (nm) of each column)."""
    kept = cal.kept
    planes = cal.local.z_nm[kept]  # each particle's plane positions, tilt-corrected nm
    z_grid = np.linspace(np.nanpercentile(planes, 5), np.nanpercentile(planes, 95), n_z)
    deltas = [cal.local_delta(z) for z in z_grid]
    px = cal.camera.pixel_size_nm
    dx = np.stack([d[0][kept] for d in deltas], axis=1) * px
    dy = np.stack([d[1][kept] for d in deltas], axis=1) * px
    domain = cal.local.shapes[cal.shape].inverse.domain[kept]
    s_grid = np.linspace(*covered_span(domain, min(MIN_PARTICLES, kept.size)), n_s)
    z_table = np.stack([cal.local_z(s)[kept] for s in s_grid], axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        z_of_column = np.nanmedian(z_table, axis=0)
    return {"x": (dx, z_grid), "y": (dy, z_grid), "z": (z_table, z_of_column)}


def evaluate(
    cal: CalibrationView,
    *,
    kinds: tuple[str, ...] = FIELD_MODELS,
    n_z: int = 41,
    n_s: int = 81,
    leave_one_out: bool | None = None,
) -> pd.DataFrame:
    """Widefield errors against z for each field model.

    Returns
    -------
    DataFrame
        One row per model, axis (x, y, z) and column: ``model``, ``axis``, ``z_nm``, and for
        the square field and the circular subset ``n_*``, ``rms_*`` (nm), ``kurtosis_*``
        (excess) and ``kurtosis_err_*``.
    """
    return _evaluate(cal, kinds, n_z, n_s, leave_one_out)[0]


def _evaluate(cal, kinds, n_z, n_s, leave_one_out):
    """:func:`evaluate`'s table, and each model's residuals (n_kept, columns) in nm by
    ``(model, axis)``."""
    columns = _columns(cal, n_z, n_s)
    x, y = cal.positions[cal.kept].T
    shape = tuple(cal.options["field_shape"])
    parts, residuals = [], {}
    for kind in kinds:
        for axis, (values, z_of_column) in columns.items():
            valid = np.isfinite(values)
            model = FieldModel.from_estimate(
                x,
                y,
                np.where(valid, values, 0.0),
                kind=kind,
                field_shape=shape,
                valid=valid,
                n_terms=cal.options.get("n_terms", 400),
            )
            resid = model.residuals(leave_one_out=leave_one_out)
            residuals[kind, axis] = resid
            table = field_errors(model, leave_one_out=leave_one_out, residuals=resid)
            table.insert(0, "z_nm", z_of_column[table["column"]])
            table.insert(0, "axis", axis)
            table.insert(0, "model", kind)
            parts.append(table.drop(columns="column"))
    return pd.concat(parts, ignore_index=True), residuals


def evaluate_figures(cal: CalibrationView, *, n_z: int = 41, n_s: int = 81) -> dict[str, Any]:
    """Fig. 5 (RMS error against z per model and axis, square and circle), Supp. Figs. 11–14
    (error maps and histograms with their excess kurtosis) and Fig. 4 (vector map of the
    apparent lateral motion between two z, and the surface of best focus); the errors on
    :func:`evaluate`'s grid of ``n_z`` z and ``n_s`` shape values."""
    import matplotlib.pyplot as plt

    errors, residuals = _evaluate(cal, FIELD_MODELS, n_z, n_s, None)
    fig5, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    for col, axis in enumerate("xyz"):
        for row, region in enumerate(("square", "circle")):
            ax = axes[row, col]
            rows = errors[errors["axis"] == axis]
            # columns that at least half of the particles cover, in order of z
            rows = rows[rows[f"n_{region}"] >= 0.5 * rows[f"n_{region}"].max()]
            for kind, group in rows.sort_values("z_nm").groupby("model"):
                ax.plot(group["z_nm"], group[f"rms_{region}"], label=kind)
            ax.set(title=f"{axis}, {region} field", ylabel="RMS error (nm)")
            if ax.get_lines():
                ax.set_yscale("log")
            else:
                mark_empty(ax, f"no {axis} errors in the {region} field")
        axes[1, col].set_xlabel("z (nm)")
    axes[0, 0].legend()
    fig5.suptitle("Widefield errors (Zernike: fit residuals; interpolants: leave-one-out)")
    fig5.tight_layout()

    kept = cal.kept
    x, y = cal.positions[kept].T
    lo, hi = np.nanpercentile(cal.local.z_nm[kept], [10, 90])
    dx0, dy0 = cal.local_delta(lo)
    dx1, dy1 = cal.local_delta(hi)
    px = cal.camera.pixel_size_nm
    fig4, (a, b) = plt.subplots(1, 2, figsize=(12, 5.2))
    um = px / 1000  # field positions in µm, like the neighbouring maps
    q = a.quiver(x * um, y * um, (dx1 - dx0)[kept] * px, (dy1 - dy0)[kept] * px, angles="xy")
    # the key inside the map's frame, lower right
    a.quiverkey(q, 0.8, 0.04, 50, "50 nm", coordinates="axes", labelpos="W")
    a.set(
        title=f"(a) apparent lateral motion from z = {lo:.0f} to {hi:.0f} nm",
        xlabel="x (µm)",
        ylabel="y (µm)",
        aspect="equal",
    )
    a.invert_yaxis()
    sc = b.scatter(x * um, y * um, c=cal.local.z_f[kept], cmap="viridis", s=12)
    fig4.colorbar(sc, ax=b, label="z of best focus after tilt removal (nm)")
    b.set(title="(b) field curvature", xlabel="x (µm)", ylabel="y (µm)", aspect="equal")
    b.invert_yaxis()
    fig4.tight_layout()
    return {
        "Fig. 5: widefield errors against z": fig5,
        "Cross-validated errors and reported uncertainties": crossval_report(cal)[1],
        "Supp. Figs. 11-14: error maps and histograms": _figure_error_distributions(
            cal, errors, residuals
        ),
        "Fig. 4: field maps": fig4,
    }


def _figure_error_distributions(cal: CalibrationView, errors: pd.DataFrame, residuals: dict) -> Any:
    """Per model (rows): the map of each particle's RMS z error over the columns (Supp. Figs.
    11, 13), and histograms of the x, y, z errors of the square field and of the circular subset
    (Supp. Figs. 12, 14), labelled with the mean over z of each column's excess kurtosis and its
    standard error, as the paper reports it (pooling columns of different spread would inflate
    it)."""
    import matplotlib.pyplot as plt

    x, y = cal.positions[cal.kept].T
    h, w = cal.options["field_shape"]
    circle = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2) <= min(h, w) / 2
    kinds = sorted({kind for kind, _ in residuals}, key=FIELD_MODELS.index)
    fig, axes = plt.subplots(len(kinds), 4, figsize=(17, 3.6 * len(kinds)), squeeze=False)
    px = cal.camera.pixel_size_nm / 1000
    for row, kind in enumerate(kinds):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per_particle = np.sqrt(np.nanmean(residuals[kind, "z"] ** 2, axis=1))
        ax = axes[row, 0]
        shown = np.isfinite(per_particle)
        if shown.any():
            sc = ax.scatter(x[shown] * px, y[shown] * px, c=per_particle[shown], s=10, cmap="magma")
            fig.colorbar(sc, ax=ax, label="RMS z error (nm)")
            ax.set(title=f"{kind}: z error per particle", xlabel="x (µm)", ylabel="y (µm)")
            ax.set_aspect("equal", adjustable="datalim")
            ax.invert_yaxis()
        else:
            mark_empty(ax, f"{kind}: no particle could be predicted\nfrom the others")
        for col, axis in enumerate("xyz", start=1):
            ax = axes[row, col]
            resid = residuals[kind, axis]
            table = errors[(errors["model"] == kind) & (errors["axis"] == axis)]
            for region, rows, color in (("square", slice(None), "0.5"), ("circle", circle, "C0")):
                values = resid[rows].ravel()
                values = values[np.isfinite(values)]
                per_column = table[f"kurtosis_{region}"].dropna()
                if values.size < 4 or per_column.empty:
                    continue
                spread = per_column.std() / np.sqrt(per_column.size)
                ax.hist(
                    values,
                    bins=60,
                    range=tuple(np.percentile(values, [0.5, 99.5])),
                    histtype="step",
                    color=color,
                    density=True,
                    label=f"{region}: kurtosis {per_column.mean():+.2f} ± {spread:.2f}",
                )
            ax.set(
                title=f"{kind}: {axis} errors", xlabel=f"{axis} error (nm)", ylabel="density (1/nm)"
            )
            if ax.patches:
                ax.legend(fontsize=8)
            else:
                mark_empty(ax, f"{kind}: too few {axis} errors\nfor a histogram")
    fig.suptitle("Widefield errors (Zernike: fit residuals; interpolants: leave-one-out)")
    fig.tight_layout()
    return fig


def crossval_report(cal: CalibrationView, *, bin_nm: float = 250.0) -> tuple[pd.DataFrame, Any]:
    """The cross-validated errors of every field model side by side (``cal.crossval``), with
    the field part of the uncertainty that ``apply`` reports for the chosen model.

    Returns
    -------
    (DataFrame, Figure)
        The table: one row per model with ``rmse_z_nm``, ``rmse_x_nm``, ``rmse_y_nm``,
        ``rmse_xy_nm``, ``in_range``, ``n`` (:func:`~latentz.calibration.crossval.
        crossval_summary`), ``chosen`` (the model ``apply`` uses) and ``reported_<axis>_nm``
        (the RMS over the held-out planes of the field σ that ``apply`` would add there); the
        figure: RMS held-out error against z per axis and model, dashed the field σ that
        ``apply`` adds at the typical held-out distance.
    """
    import matplotlib.pyplot as plt

    from latentz.calibration.crossval import crossval_summary
    from latentz.calibration.errors import field_sigma

    table = cal.crossval
    summary = crossval_summary(table)
    summary["chosen"] = summary.index == cal.field_model
    for axis in "xyz":
        reported = []
        for kind in summary.index:
            rows = table[(table["model"] == kind) & table["in_range"]]
            sigma = field_sigma(table, kind, axis, rows["z_nm"], rows["distance_px"])
            reported.append(float(np.sqrt(np.mean(sigma**2))) if sigma.size else np.nan)
        summary[f"reported_{axis}_nm"] = reported
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), sharex=True)
    for ax, axis in zip(axes, "xyz", strict=True):
        for kind, rows in table[table["in_range"]].groupby("model"):
            z = rows["z_nm"].to_numpy()
            edges = np.arange(np.min(z), np.max(z) + bin_nm, bin_nm)
            which = np.digitize(z, edges)
            err2 = rows[f"err_{axis}_nm"].to_numpy() ** 2
            centres = [z[which == k].mean() for k in np.unique(which)]
            rms = [np.sqrt(err2[which == k].mean()) for k in np.unique(which)]
            (line,) = ax.plot(centres, rms, label=kind)
            grid = np.linspace(np.min(z), np.max(z), 100)
            typical = np.sqrt(np.mean(rows["distance_px"] ** 2))
            sigma = field_sigma(table, kind, axis, grid, np.full(grid.size, typical))
            ax.plot(grid, sigma, "--", color=line.get_color())
        ax.set(xlabel="z (nm)", ylabel=f"{axis}: RMS held-out error (nm)", yscale="log")
    axes[0].legend(title=f"apply uses {cal.field_model}")
    fig.suptitle(
        "Leave-one-particle-out errors of each field model (dashed: the field σ apply adds)"
    )
    fig.tight_layout()
    return summary, fig

"""Cross-validation of the whole widefield prediction, and the choice of field model.

A field model is judged where it is used: between calibration particles. Each kept particle is
held out in turn, the widefield model is built from the others, and the held-out particle's own
calibration is predicted at its place: for every plane of its monotonic range, z from the shape
value s measured there, smoothed by a local cubic over a few planes (not its order-16 forward
model, which near focus misses noise-free curves by several times the noise of bright beads),
then Δx', Δy' at the predicted z. The errors (predicted minus the plane's z and its own lateral
models, nm) are the field model's error; a spot's fit precision and the local model's σ are
accounted separately (:mod:`latentz.calibration.errors`).

To keep the cost at a few model builds, particles are held out in ``n_groups`` groups spread over
the field (every ``n_groups``-th particle in a random order): each build then uses
``1 − 1/n_groups`` of the particles, so the errors are those of a slightly sparser calibration
(conservative by a few percent for 16 groups).

The choice is judged by what users localize: emitters dimmer than the calibration beads, whose
own precision σ_fit(z) adds to the field model's error. Far from focus s changes little with z,
so there both σ_fit and the held-out errors of every model grow large (hundreds of nm at the ends
of the particles' monotonic ranges), and the RMS of the held-out errors is ruled by those few
planes. :func:`choose_field_model` therefore ranks the models by the mean over the held-out
planes of the total error of a typical emitter, ``sqrt(σ_fit² + err_z²)`` (``typical_z_nm``;
σ_fit the Cramér–Rao σ_z of an emitter of :data:`TYPICAL_PHOTONS` photons imaged like the
held-out particle at that plane, :func:`~latentz.calibration.precision.crlb_sigma_z`). The models
compared are those that predict at least 95 % as many held-out planes as ``nearest`` and lose
no held-out particle (predict at least half the planes ``nearest`` predicts of each), and they
are compared on the planes that every one of them predicts: a model that predicts more planes
far from focus, where every model errs most, would otherwise rank behind one that leaves them
out. It takes the best of those no worse than ``nearest`` there in that and in lateral RMSE;
``nearest`` is always eligible, so the choice is never worse than it. A model that loses
particles is named, with the count, in a warning. A table without σ_fit is ranked by the z
RMSE.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from scipy.signal import savgol_coeffs, savgol_filter
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["CROSSVAL_COLUMNS", "LOST_SHARE", "MIN_FIELD_PARTICLES", "TYPICAL_PHOTONS",
           "crossval", "choose_field_model", "crossval_summary", "emitter_sigma_z",
           "lost_particles", "predict", "resolve_auto", "shared_planes",
           "smoothed_noise"]  # fmt: skip

CROSSVAL_COLUMNS = ("model", "particle", "x", "y", "distance_px", "z_nm", "in_range",
                    "err_z_nm", "err_x_nm", "err_y_nm")  # fmt: skip

#: Planes of the local cubic (Savitzky-Golay) that takes the noise of bright beads off the
#: held-out shape values, without the order-16 forward model's misfit near focus.
_SMOOTH_PLANES = 7

#: Fewer kept particles than this leave no field to model: "auto" takes ``nearest``.
MIN_FIELD_PARTICLES = 12

#: A held-out particle is lost by a model that predicts fewer than this share of the planes
#: that ``nearest`` predicts of it.
LOST_SHARE = 0.5

#: Brightness of the typical emitter that ranks the models: the upper end of single molecules
#: (100-10,000 photons), where the field model's error is not yet hidden by the fit's precision.
TYPICAL_PHOTONS = 1e4


def _subset(cal: CalibrationView, keep: np.ndarray, kind: str) -> Any:
    """The calibration restricted to the particles ``keep`` (bool, n) with field model ``kind``."""
    options = {**cal.options, "field_model": kind}
    return replace(cal, culled=cal.culled | ~keep, options=options, _cache={})


def predict(cal: CalibrationView, x_px: np.ndarray, y_px: np.ndarray, s: np.ndarray) -> tuple:
    """z (nm), Δx', Δy' (px) and in_range for shape values ``s`` at (x, y) with ``cal``'s field
    model, as :meth:`Calibration.apply` computes them."""
    wide = cal.widefield
    if wide is not None:
        z, dx, dy, ok = wide(x_px, y_px, s, iterations=cal.options.get("iterations", 0))
        return z, dx, dy, ok
    p = cal.nearest(x_px, y_px)
    z = cal.inverse_z(s, p)
    ok = np.isfinite(z)
    zq = np.where(ok, z, 0.0)
    return z, cal.local.dx[p](zq), cal.local.dy[p](zq), ok


def _held_out_planes(cal: CalibrationView, particles: np.ndarray) -> pd.DataFrame:
    """Every plane of each particle's monotonic range whose measured shape value its own inverse
    model covers (noise takes the end planes' values past it): its z, that s (a local cubic over
    :data:`_SMOOTH_PLANES` planes, where the particle has a value at every plane) and
    Δx'(z), Δy'(z)."""
    model = cal.local.shapes[cal.shape]
    z = cal.local.z_nm[particles]
    lo, hi = model.z_range[particles, 0:1], model.z_range[particles, 1:2]
    inside = (z >= lo) & (z <= hi)
    vals = np.array(model.values[particles])
    full = _smoothed(vals)
    if full.any():
        vals[full] = savgol_filter(vals[full], _SMOOTH_PLANES, 3, axis=1)
    rows, cols = np.nonzero(inside & np.isfinite(vals))
    covered = model.inverse[particles[rows]].contains(vals[rows, cols])
    rows, cols = rows[covered], cols[covered]
    p = particles[rows]
    zz = z[rows, cols]
    return pd.DataFrame(
        {
            "particle": p,
            "x": cal.positions[p, 0],
            "y": cal.positions[p, 1],
            "z_nm": zz,
            "s": vals[rows, cols],
            "dx": cal.local.dx[p](zz),
            "dy": cal.local.dy[p](zz),
        }
    )


def _smoothed(values: np.ndarray) -> np.ndarray:
    """(n,) which rows of shape values (n, n_z) :func:`_held_out_planes` smooths: those with a
    value at every plane, of at least :data:`_SMOOTH_PLANES` planes."""
    return np.isfinite(values).all(axis=1) & (values.shape[1] >= _SMOOTH_PLANES)


def smoothed_noise(cal: CalibrationView, particles: np.ndarray) -> np.ndarray:
    """(n,) the share of a held-out particle's own noise in s (1σ) left in its held-out
    shape values: the local cubic's centre weights' root sum of squares (0.58) where
    :func:`_held_out_planes` smooths them, else 1."""
    gain = float(np.sqrt(np.sum(savgol_coeffs(_SMOOTH_PLANES, 3) ** 2)))
    values = cal.local.shapes[cal.shape].values[np.asarray(particles, dtype=np.int64)]
    return np.where(_smoothed(values), gain, 1.0)


def crossval(
    cal: CalibrationView,
    kinds: tuple[str, ...] = ("nearest", "natural", "curves", "zernike"),
    *,
    n_groups: int = 16,
    seed: int = 0,
) -> pd.DataFrame:
    """Held-out errors of every field model in ``kinds`` (module notes).

    Returns
    -------
    DataFrame
        One row per model, held-out particle and plane (:data:`CROSSVAL_COLUMNS`): the particle's
        position (px), its distance to the nearest particle the model was built from (px), its
        true z (nm, tilt-corrected), whether the model predicts it, and the
        errors of z, and of the corrected x and y (nm; the lateral error includes the effect of
        the z error on Δx', Δy').
    """
    kept = cal.kept
    if kept.size < 2:  # nothing to hold out: an empty table of the right types
        empty = {c: np.zeros(0) for c in CROSSVAL_COLUMNS}
        empty.update(model=np.zeros(0, dtype=str), particle=np.zeros(0, dtype=np.int64),
                     in_range=np.zeros(0, dtype=bool))  # fmt: skip
        return pd.DataFrame(empty)
    px = cal.camera.pixel_size_nm
    groups = np.random.default_rng(seed).permutation(kept.size) % min(n_groups, kept.size)
    parts = []
    for kind in kinds:
        for g in np.unique(groups):
            out = kept[groups == g]
            keep = np.ones(cal.culled.size, dtype=bool)
            keep[out] = False
            planes = _held_out_planes(cal, out)
            others = cKDTree(cal.positions[kept[groups != g]])
            distance = others.query(planes[["x", "y"]].to_numpy())[0]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # a few columns with fewer terms
                try:
                    z, dx, dy, ok = predict(
                        _subset(cal, keep, kind), planes["x"], planes["y"], planes["s"]
                    )
                except ValueError:  # too few particles left for this model
                    z = dx = dy = np.full(len(planes), np.nan)
                    ok = np.zeros(len(planes), dtype=bool)
            parts.append(
                pd.DataFrame(
                    {
                        "model": kind,
                        "particle": planes["particle"],
                        "x": planes["x"],
                        "y": planes["y"],
                        "distance_px": distance,
                        "z_nm": planes["z_nm"],
                        "in_range": ok,
                        "err_z_nm": np.where(ok, z - planes["z_nm"], np.nan),
                        "err_x_nm": np.where(ok, (planes["dx"] - dx) * px, np.nan),
                        "err_y_nm": np.where(ok, (planes["dy"] - dy) * px, np.nan),
                    }
                )
            )
    return pd.concat(parts, ignore_index=True)


def emitter_sigma_z(
    cal: CalibrationView, table: pd.DataFrame, photons: float = TYPICAL_PHOTONS
) -> np.ndarray:
    """σ_z (nm) of an emitter of ``photons`` photons imaged like each row's held-out particle at
    that plane (:func:`~latentz.calibration.precision.crlb_sigma_z`); NaN where unknown."""
    from latentz.calibration.precision import crlb_sigma_z

    sigma = crlb_sigma_z(cal.local, cal.traces, cal.shape, photons, roi_size=cal.roi_size,
                         readnoise=cal.camera.readnoise)  # fmt: skip
    p = table["particle"].to_numpy(dtype=np.int64)
    z = table["z_nm"].to_numpy(dtype=np.float64)
    plane = np.argmin(np.abs(cal.local.z_nm[p] - z[:, None]), axis=1) if p.size else p
    return sigma[p, plane]


def crossval_summary(table: pd.DataFrame, sigma_fit_nm: np.ndarray | None = None) -> pd.DataFrame:
    """Per model: ``rmse_z_nm``, ``rmse_x_nm``, ``rmse_y_nm``, ``rmse_xy_nm`` (x and y pooled)
    of the predicted planes, their fraction ``in_range`` and the count ``n``; with
    ``sigma_fit_nm`` (one per row, :func:`emitter_sigma_z`) also ``typical_z_nm``, the mean of
    ``sqrt(σ_fit² + err_z²)`` over the predicted planes where σ_fit is known; with a
    ``particle`` column, ``lost`` (:func:`lost_particles`) of the ``held_out`` particles that
    ``nearest`` predicts."""
    rows = {}
    table = table.assign(sigma_fit=np.nan if sigma_fit_nm is None else sigma_fit_nm)
    for kind, part in table.groupby("model", sort=False):
        used = part[part["in_range"]]
        rms = {a: float(np.sqrt(np.mean(used[f"err_{a}_nm"] ** 2))) for a in "xyz"}
        known = used[np.isfinite(used["sigma_fit"])]
        typical = np.mean(np.hypot(known["sigma_fit"], known["err_z_nm"])) if len(known) else np.nan
        rows[kind] = {
            "typical_z_nm": float(typical),
            "rmse_z_nm": rms["z"],
            "rmse_x_nm": rms["x"],
            "rmse_y_nm": rms["y"],
            "rmse_xy_nm": float(np.sqrt((rms["x"] ** 2 + rms["y"] ** 2) / 2)),
            "in_range": float(part["in_range"].mean()),
            "n": len(used),
        }
    summary = pd.DataFrame.from_dict(rows, orient="index").rename_axis("model")
    if "particle" in table and "nearest" in summary.index:
        summary["lost"], summary["held_out"] = lost_particles(table)
    return summary


def lost_particles(table: pd.DataFrame) -> tuple[pd.Series, int]:
    """Per model of a :func:`crossval` table, how many held-out particles it loses (predicts
    fewer than :data:`LOST_SHARE` of the planes ``nearest`` predicts of them), and how many
    particles ``nearest`` predicts at all."""
    counts = table.groupby(["model", "particle"])["in_range"].sum().unstack("model", fill_value=0)
    base = counts["nearest"]
    held = base > 0
    lost = (counts[held].lt(LOST_SHARE * base[held], axis=0)).sum(axis=0)
    return lost.astype(int), int(held.sum())


def choose_field_model(
    table: pd.DataFrame, sigma_fit_nm: np.ndarray | None = None, *, coverage: float = 0.95
) -> str:
    """The model ``auto`` takes from a :func:`crossval` table (``sigma_fit_nm`` as
    :func:`crossval_summary` takes it). The models that predict at least ``coverage`` x as many
    held-out planes as ``nearest`` and lose no held-out particle are compared on the planes
    that each of them predicts (:func:`shared_planes`): one that predicts more planes, far from
    focus where every model errs most, is not judged on planes the others leave out. Of those
    no worse than ``nearest`` there in typical z error (``typical_z_nm``; the z RMSE where
    σ_fit is not known) and in lateral RMSE, the one with the smallest typical z error."""
    whole = crossval_summary(table, sigma_fit_nm)
    base = whole.loc["nearest"]
    fair = whole[
        (whole["in_range"] >= coverage * base["in_range"])
        & (whole["lost"] == 0 if "lost" in whole else True)
    ].index.union(["nearest"])
    rows = shared_planes(table, fair)
    sigma = None if sigma_fit_nm is None else np.asarray(sigma_fit_nm, dtype=np.float64)[rows]
    summary = crossval_summary(table[rows], sigma)
    if "nearest" not in summary.index:  # no held-out plane that every model compared predicts
        return "nearest"
    base = summary.loc["nearest"]
    known = "typical_z_nm" in summary and np.isfinite(summary["typical_z_nm"]).all()
    rank = "typical_z_nm" if known else "rmse_z_nm"
    eligible = summary[
        (summary[rank] <= base[rank]) & (summary["rmse_xy_nm"] <= base["rmse_xy_nm"])
    ]
    return str(eligible[rank].idxmin()) if len(eligible) else "nearest"


def shared_planes(table: pd.DataFrame, models: Iterable[str]) -> np.ndarray:
    """Whether each row of a :func:`crossval` table is one of ``models``' prediction of a
    held-out plane (its ``particle`` and ``z_nm``) that every one of them predicts."""
    models = list(models)
    ours = table["model"].isin(models).to_numpy() & table["in_range"].to_numpy(bool)
    keys = pd.MultiIndex.from_frame(table[["particle", "z_nm"]])
    predicted = pd.Series(table["model"].to_numpy()[ours], index=keys[ours])
    count = predicted.groupby(level=[0, 1]).nunique()
    return ours & keys.isin(count.index[count.to_numpy() == len(models)])


def resolve_auto(cal: CalibrationView) -> str:
    """``field_model="auto"``: the model :func:`choose_field_model` picks from ``cal.crossval``;
    "nearest", with a warning, below :data:`MIN_FIELD_PARTICLES` kept particles."""
    if cal.kept.size < MIN_FIELD_PARTICLES:
        warnings.warn(
            f"field_model='auto': only {cal.kept.size} kept calibration particles (a field model "
            f"needs {MIN_FIELD_PARTICLES}); using 'nearest'.",
            UserWarning,
            stacklevel=3,
        )
        return "nearest"
    table = cal.crossval
    lost, held_out = lost_particles(table)
    for model, count in lost[lost > 0].items():
        warnings.warn(
            f"field_model='auto': {model!r} loses {count} of {held_out} held-out "
            f"calibration particles (it predicts under half the planes 'nearest' predicts of "
            f"them), so it is not chosen.",
            UserWarning,
            stacklevel=3,
        )
    return choose_field_model(table, emitter_sigma_z(cal, table))

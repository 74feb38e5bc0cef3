"""Held-out z error of a dim emitter imaged like a calibration particle.

A single molecule of 10³–10⁴ photons is not measured like a 10⁵-photon bead: its Gaussian fit
is biased by the background (:mod:`~latentz.calibration.dimming`), and
:meth:`~latentz.calibration.Calibration.apply` removes that bias with the refits of the
calibration particle nearest the spot. How well that transfers between particles depends on
the ROI (a large ROI holds more of the defocused ring, whose bias changes across the field), and
the bright particles' own cross-validation cannot see it.

So each kept particle is held out and its image at every plane is seen as an emitter of
``photons`` photons over the particle's own background: its shape value is the particle's own
refit at that emitter's background ratio c (:func:`~latentz.calibration.dimming.shape_shift`
from its own traces), the nearest *other* kept particle's refits at the same z correct it as
``apply`` does, and that particle's inverse model gives z. The error (nm) is that z minus the
plane's (tilt-corrected) z: field, dimming transfer and the particles' own heights together;
the fit's precision is not in it (the refits are of the bright image).

Localized by each of its first to fourth nearest other particles (:data:`PAIR_RANKS`), the
same held-out particle is an emitter at a growing distance from the particle whose model it is
given:
:func:`pair_table` holds these errors with the distances, the z error of a dim emitter as it
grows with the distance to the particle that localizes it, measured at the user's own
particles (:meth:`~latentz.calibration.Calibration.apply` reads it with
:func:`~latentz.calibration.errors.field_sigma`). For the joint readout of z
(:mod:`~latentz.calibration.readout`) the held-out particle's wx, wy, ρ, each corrected alike, are
read on its neighbour's curves instead, weighted by the Cramér–Rao covariance of that dim image:
the two readouts err differently between particles, and each spot's σ takes its own readout's.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.calibration.dimming import SHAPE_DIM_COLUMNS, background_ratio, shape_shift
from latentz.calibration.readout import SHAPE_PARAMS, joint_z, shape_covariance
from latentz.calibration.rows import interp_rows, row_weights
from latentz.calibration.shape import shape_value

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["PAIR_RANKS", "TRANSFER_BIN_NM", "dim_held_out", "pair_table", "transfer_sigma"]

#: Width of the z bins in which :func:`transfer_sigma` pools the held-out errors, nm.
TRANSFER_BIN_NM = 250.0
#: Fewest held-out planes a bin of :func:`transfer_sigma` needs.
_MIN_PER_BIN = 30
#: Which nearest other particles localize each held-out particle in :func:`pair_table`.
PAIR_RANKS = (1, 2, 3, 4)
_PAIR_COLUMNS = ("c", "model", "particle", "z_nm", "distance_px", "err_z_nm", "in_range")


def _partners(cal: CalibrationView, rank: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kept particles with a valid inverse model, the ``rank``-th nearest other one of
    each, and its distance (px); all empty where there are no more than ``rank`` of them."""
    rows = cal.kept[cal.local.shapes[cal.shape].inverse.valid[cal.kept]]
    if rows.size <= rank:
        return (np.zeros(0, int),) * 2 + (np.zeros(0),)
    distance, nearest = cKDTree(cal.positions[rows]).query(cal.positions[rows], k=rank + 1)
    return rows, rows[nearest[:, rank]], distance[:, rank]


def dim_held_out(
    cal: CalibrationView, *, ratio: float, rank: int = 1, readout: str = "shape"
) -> np.ndarray:
    """(n, n_z) z error (nm) of an emitter of background ratio ``ratio`` = (b + readnoise²) / A
    imaged like each kept particle at each plane, localized
    with its ``rank``-th nearest other kept particle's refits and inverse model (module notes),
    or with ``readout="joint"`` its wx, wy, ρ read on that particle's curves
    (:func:`_joint_estimate`); NaN for culled particles and where the model does not cover it."""
    local, traces, shape = cal.local, cal.traces, cal.shape
    model = local.shapes[shape]
    n, n_z = model.values.shape
    errors = np.full((n, n_z), np.nan)
    rows, partners, _ = _partners(cal, rank)
    if rows.size == 0:
        return errors
    i = np.repeat(rows, n_z)
    k = np.tile(np.arange(n_z), rows.size)
    p = np.repeat(partners, n_z)
    z = local.z_nm[i, k]
    readnoise = cal.camera.readnoise
    ref = model.amplitude_ref

    def shape_of(owner: np.ndarray):
        def of(a, wx, wy, rho):
            return shape_value(shape, wx, wy, rho, a, theta=local.theta,
                               amplitude_ref=ref[owner])  # fmt: skip

        return of

    def own(name: str) -> np.ndarray:
        return traces[name][i, k]

    at = row_weights(local.z_nm, p, z)

    def neighbour(name: str) -> np.ndarray:
        """The partner particle's trace at each held-out plane's z (end values held)."""
        return interp_rows(local.z_nm, traces[name], p, z, at)

    c_spot = np.full(i.size, float(ratio))
    c_own = background_ratio(own("background"), own("amplitude"), readnoise)
    c_near = background_ratio(neighbour("background"), neighbour("amplitude"), readnoise)
    refits = all(name in traces.data for name in SHAPE_DIM_COLUMNS)

    def seen(value: np.ndarray, owner_of: Callable) -> np.ndarray:
        """``value`` of the held-out image at c_spot, less the partner's correction to it."""
        if not refits:  # no refits: no correction
            return value
        shift = shape_shift(owner_of(i), own, c_spot, c_own)
        correction = shape_shift(owner_of(p), neighbour, c_spot, c_near)
        return value + shift - np.where(np.isfinite(correction), correction, 0.0)

    if readout == "joint":  # each of wx, wy, ρ shifted as a shape value is
        fitted = np.column_stack([
            seen(own(name), lambda _, j=j: lambda a, wx, wy, rho: (wx, wy, rho)[j])
            for j, name in enumerate(SHAPE_PARAMS)])  # fmt: skip
        amplitude = own("amplitude")
        background = np.where(c_spot > c_own, c_spot * amplitude - readnoise**2,
                              own("background"))  # fmt: skip
        errors[i, k] = _joint_estimate(cal, p, fitted, amplitude, background) - z
        return errors
    s = seen(model.values[i, k], shape_of)
    inverse = model.inverse[p]
    inside = inverse.contains(s) & np.isfinite(s)
    estimate = np.where(inside, inverse(np.where(inside, s, 0.0)), np.nan)
    errors[i, k] = estimate - z
    return errors


def _joint_estimate(cal: CalibrationView, p: np.ndarray, fitted: np.ndarray, amplitude: np.ndarray,
                    background: np.ndarray) -> np.ndarray:  # fmt: skip
    """z (nm) of held-out images of fitted (wx, wy, ρ) ``fitted`` (m, 3), peak ``amplitude``
    and ``background`` (photoelectrons per pixel) read jointly on particles ``p``'s curves
    (:func:`~latentz.calibration.readout.joint_z`), weighted as an emitter's fit is: by the
    Cramér–Rao covariance of that image (its scale, and the curves' scatter, do not move the
    minimum of a dim emitter's distance, whose fit noise rules it)."""
    params = np.column_stack([np.zeros((len(p), 2)), amplitude, np.maximum(background, 0.0),
                              fitted])  # fmt: skip
    cov = shape_covariance(params, None, None, roi_size=cal.roi_size,
                           readnoise=cal.camera.readnoise)  # fmt: skip
    no_scatter = np.zeros((len(cal.local.z_nm), len(SHAPE_PARAMS)))
    return joint_z(cal.curves_at, cal.local.z_nm, no_scatter, p, fitted, cov).z_nm


def transfer_sigma(cal: CalibrationView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How much the dimming correction errs when it is carried from the nearest particle to a
    spot: ``(z_nm, log_c, sigma_nm)``, the RMS over the kept particles of the held-out error at
    background ratio c (each of :data:`~latentz.calibration.dimming.LEVELS`) minus that of the
    bright image itself (:func:`dim_held_out`, at the planes :func:`pair_table` counts), in z
    bins :data:`TRANSFER_BIN_NM` wide (bin centres ``z_nm``; bins with fewer than 30 planes
    merged into the next) by ``log_c``;
    ``sigma_nm`` (n_levels, n_bins). Empty where there are no refits."""
    from latentz.calibration.dimming import LEVELS

    if not all(name in cal.traces.data for name in SHAPE_DIM_COLUMNS):
        return np.zeros(0), np.zeros(0), np.zeros((0, 0))
    z = cal.local.z_nm
    bright = _judged(cal, dim_held_out(cal, ratio=0.0), 1)  # below every particle's own c
    differences = [_judged(cal, dim_held_out(cal, ratio=c), 1) - bright for c in LEVELS]
    known = np.isfinite(bright) & np.all(np.isfinite(differences), axis=0)
    if known.sum() < _MIN_PER_BIN:
        return np.zeros(0), np.zeros(0), np.zeros((0, 0))
    zz = z[known]
    order = np.argsort(zz)
    zz = zz[order]
    edges = np.arange(zz[0], zz[-1] + TRANSFER_BIN_NM, TRANSFER_BIN_NM)
    bins = np.searchsorted(edges, zz, side="right") - 1
    centres, sigmas, group = [], [], np.zeros(zz.size, bool)
    for b in np.unique(bins):
        group |= bins == b
        if group.sum() >= _MIN_PER_BIN or b == bins[-1]:
            centres.append(float(np.mean(zz[group])))
            sigmas.append([np.sqrt(np.mean(d[known][order][group] ** 2)) for d in differences])
            group[:] = False
    return np.array(centres), np.log(np.asarray(LEVELS)), np.array(sigmas).T


def _judged(cal: CalibrationView, errors: np.ndarray, rank: int) -> np.ndarray:
    """:func:`dim_held_out`'s ``errors`` (n, n_z) at ``rank``, NaN where a held-out plane does
    not count: outside the held-out particle's monotonic range (as crossval holds out) or with
    its estimate outside the span its partner was imaged over (as ``apply`` requires). There
    the partner's inverse is flat or extrapolated and its error says nothing of a spot's."""
    rows, partners, _ = _partners(cal, rank)
    out = np.full_like(errors, np.nan)
    if rows.size == 0:
        return out
    z = cal.local.z_nm[rows]
    lo, hi = cal.z_span_nm[partners, :1], cal.z_span_nm[partners, 1:]
    own = cal.local.shapes[cal.shape].z_range[rows]  # its monotonic range, as crossval's
    err = errors[rows]
    with np.errstate(invalid="ignore"):
        known = (z >= own[:, :1]) & (z <= own[:, 1:]) & (z + err >= lo) & (z + err <= hi)
    out[rows] = np.where(known, err, np.nan)
    return out


def pair_table(cal: CalibrationView, readout: str = "shape") -> pd.DataFrame:
    """Held-out z errors of each kept particle seen as an emitter at each background ratio c of
    :data:`~latentz.calibration.dimming.LEVELS` (only the bright image where there are no
    refits) and localized by each of its :data:`PAIR_RANKS` nearest other particles
    (:func:`dim_held_out` with ``readout``). Columns: ``c``, ``model`` ("pairs"),
    ``particle``, ``z_nm``, ``distance_px`` (to the particle that localized it), ``err_z_nm``
    and ``in_range`` (the
    error is known, at a plane of the held-out particle's monotonic range, as
    :func:`~latentz.calibration.crossval.crossval` holds out, and its z within the span that
    particle was imaged over, as :meth:`~latentz.calibration.Calibration.apply` requires), the
    columns :func:`~latentz.calibration.errors.field_sigma` reads."""
    from latentz.calibration.dimming import LEVELS

    refits = all(name in cal.traces.data for name in SHAPE_DIM_COLUMNS)
    n_z = cal.local.z_nm.shape[1]
    frames = []
    for rank in PAIR_RANKS:
        rows, partners, distance = _partners(cal, rank)
        z = cal.local.z_nm[rows]
        for c in (LEVELS if refits else (0.0,)) if rows.size else ():
            held = dim_held_out(cal, ratio=c, rank=rank, readout=readout)
            err = _judged(cal, held, rank)[rows].ravel()
            frames.append(pd.DataFrame({
                "c": c, "model": "pairs", "particle": np.repeat(rows, n_z),
                "z_nm": z.ravel(), "distance_px": np.repeat(distance, n_z),
                "err_z_nm": err, "in_range": np.isfinite(err)}))  # fmt: skip
    if not frames:
        return pd.DataFrame({name: [] for name in _PAIR_COLUMNS})
    return pd.concat(frames, ignore_index=True)

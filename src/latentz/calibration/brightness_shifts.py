"""How a spot's own brightness shifts what its fit reads: the shape value, the fitted wx, wy,
ρ and the fitted centre of a spot dimmer than its calibration particle, from the particle's
dimmed refits at the spot's z (:mod:`latentz.calibration.dimming`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from latentz.calibration.dimming import (
    DIM_COLUMNS,
    background_ratio,
    dimmest,
    position_shift,
    shape_shift,
)
from latentz.calibration.rows import interp_rows
from latentz.calibration.shape import shape_value

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["position_shifts", "shape_params_shift", "shape_value_shift", "shift_by_plane"]


def shape_value_shift(
    cal: Calibration, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
    z: np.ndarray, ref: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """How much brighter-than-the-spot calibration images shift the spots' shape values
    (:func:`~latentz.calibration.dimming.shape_shift`), from particle ``p``'s refits at the
    spots' z (:func:`_dimming_terms`); 0 where that is unknown."""

    def shape_of(a, wx, wy, rho):
        return shape_value(cal.shape, wx, wy, rho, a, theta=cal.local.theta,
                           amplitude_ref=ref)  # fmt: skip

    shift = shape_shift(shape_of, *_dimming_terms(cal, amplitude, background, p, z))
    return np.where(np.isfinite(shift), shift, 0.0)


def position_shifts(
    cal: Calibration, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
    z: np.ndarray,
) -> dict[str, np.ndarray]:  # fmt: skip
    """How much brighter-than-the-spot calibration images shift the spots' fitted x and y
    (px, :func:`~latentz.calibration.dimming.position_shift`), from particle ``p``'s
    refits at the spots' z (:func:`_dimming_terms`); 0 where that is unknown."""
    shift = position_shift(*_dimming_terms(cal, amplitude, background, p, z))
    shift = np.where(np.isfinite(shift), shift, 0.0)
    return {"x": shift[:, 0], "y": shift[:, 1]}


def shape_params_shift(cal: Calibration, cols: dict, p: np.ndarray, z: np.ndarray,
                       plane: np.ndarray | None = None) -> np.ndarray | None:  # fmt: skip
    """(n, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns ``cols`` on
    particles ``p`` at z (nm) (:func:`~latentz.calibration.dimming.shape_shift` of the three
    at once, from one read of :func:`_dimming_terms`; 0 where unknown), or None where the
    calibration has no dimmed refits or the spots no background. ``plane`` (n,), if given,
    is the index of the particle's plane at z, read without interpolation."""
    if "background" not in cols or "dim0_wx" not in cal.traces.data:
        return None
    terms = _dimming_terms(cal, cols["amplitude"], cols["background"], p, z, plane)
    shift = shape_shift(lambda a, wx, wy, rho: np.column_stack([wx, wy, rho]), *terms)
    return np.where(np.isfinite(shift), shift, 0.0)


def shift_by_plane(cal: Calibration, cols: dict, p: np.ndarray) -> np.ndarray | None:
    """(n, planes, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns
    ``cols`` on particles ``p`` at each of the particle's planes
    (:func:`shape_params_shift` there), or None where the calibration has no dimmed refits
    or the spots no background."""
    if "background" not in cols or "dim0_wx" not in cal.traces.data:
        return None
    planes = cal.local.z_nm[p]
    n, n_z = planes.shape
    rows = {name: np.repeat(cols[name], n_z) for name in ("amplitude", "background")}
    index = np.tile(np.arange(n_z), n)
    shift = shape_params_shift(cal, rows, np.repeat(p, n_z), planes.ravel(), index)
    return shift.reshape(n, n_z, 3)


def _dimming_terms(
    cal: Calibration, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
    z: np.ndarray, plane: np.ndarray | None = None,
) -> tuple[Callable[[str], np.ndarray], np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """What the brightness corrections of spots of fitted ``amplitude`` and ``background``
    on particles ``p`` at ``z`` read: particle ``p``'s traces at z (``trace_at(name)``),
    the spots' background ratio c, the particle's own c there, and the c the correction
    starts from.

    Where the calibration particles' brightness follows their size (their heights were
    taken off, :mod:`latentz.calibration.heights`), spots within the calibration's own range
    of brightness at their depth (up to its dimmest particles,
    :func:`~latentz.calibration.dimming.dimmest`) are not shifted; beyond that edge the shift
    starts there, and its start moves back to the particle's own ratio c as the spot's c
    goes as far again (in log c) beyond the edge, so that dim emitters get the whole shift
    from their particle's own fit (:mod:`~latentz.calibration.dimming` notes)."""
    readnoise = cal.camera.readnoise
    index, stacked = _brightness_traces(cal)
    if plane is None:
        read = interp_rows(cal.local.z_nm, stacked, p, z)  # every trace in one lookup
    else:
        read = stacked[p, plane]

    def trace_at(name: str) -> np.ndarray:
        return read[:, index[name]]

    c_spot = background_ratio(background, amplitude, readnoise)
    c_own = background_ratio(trace_at("background"), trace_at("amplitude"), readnoise)
    c_from = c_own
    if cal.options.get("particle_heights", {}).get("applied"):
        if "dimmest" not in cal._cache:
            rows = cal.kept
            c = background_ratio(cal.traces["background"][rows],
                                 cal.traces["amplitude"][rows], readnoise)  # fmt: skip
            cal._cache["dimmest"] = dimmest(cal.local.z_nm[rows], c)
        edge = np.fmax(c_own, np.interp(z, *cal._cache["dimmest"]))
        # the start fades from the edge back to the particle's own c as far again beyond it
        with np.errstate(invalid="ignore", divide="ignore"):
            c_from = np.clip(edge**2 / c_spot, c_own, edge)
    return trace_at, c_spot, c_own, c_from


def _brightness_traces(cal: Calibration) -> tuple[dict[str, int], np.ndarray]:
    """The traces the brightness corrections read (the calibration's own fit and its
    refits, :data:`~latentz.calibration.dimming.DIM_COLUMNS`) stacked (n, n_z, k), so
    that one lookup reads them all, and each name's index in the last axis; computed once
    (k ≤ 47 traces: about 45 MB for 1000 particles of 121 planes)."""
    if "brightness_traces" not in cal._cache:
        names = [name for name in ("amplitude", "wx", "wy", "rho", "background", *DIM_COLUMNS)
                 if name in cal.traces.data]  # fmt: skip
        stacked = np.stack([cal.traces[name] for name in names], axis=2)
        cal._cache["brightness_traces"] = ({n: k for k, n in enumerate(names)}, stacked)
    return cal._cache["brightness_traces"]

"""How a spot's own brightness shifts what its fit reads: the shape value, the fitted wx, wy,
ρ and the fitted centre of a spot dimmer than its calibration particle, from the particle's
dimmed refits at the spot's z (:mod:`latentz.calibration.dimming`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from latentz.calibration.dimming import (
    DIM_COLUMNS,
    Levels,
    background_ratio,
    dimmest,
    level_positions,
    level_value,
    position_shift,
    shape_levels,
    shape_shift,
)
from latentz.calibration.rows import interp_rows
from latentz.calibration.shape import shape_value

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["position_shifts", "shape_params_shift", "shape_value_shift", "shift_by_plane"]


def shape_value_shift(
    cal: CalibrationView, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
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
    cal: CalibrationView, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
    z: np.ndarray,
) -> dict[str, np.ndarray]:  # fmt: skip
    """How much brighter-than-the-spot calibration images shift the spots' fitted x and y
    (px, :func:`~latentz.calibration.dimming.position_shift`), from particle ``p``'s
    refits at the spots' z (:func:`_dimming_terms`); 0 where that is unknown."""
    shift = position_shift(*_dimming_terms(cal, amplitude, background, p, z))
    shift = np.where(np.isfinite(shift), shift, 0.0)
    return {"x": shift[:, 0], "y": shift[:, 1]}


def shape_params_shift(cal: CalibrationView, cols: dict, p: np.ndarray,
                       z: np.ndarray) -> np.ndarray | None:  # fmt: skip
    """(n, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns ``cols`` on
    particles ``p`` at z (nm) (:func:`~latentz.calibration.dimming.shape_shift` of the three
    at once, from one read of :func:`_dimming_terms`; 0 where unknown), or None where the
    calibration has no dimmed refits or the spots no background."""
    if "background" not in cols or "dim0_wx" not in cal.traces.data:
        return None
    shift = shape_shift(_shape_params, *_dimming_terms(cal, cols["amplitude"],
                                                       cols["background"], p, z))  # fmt: skip
    return np.where(np.isfinite(shift), shift, 0.0)


def shift_by_plane(cal: CalibrationView, cols: dict, p: np.ndarray) -> np.ndarray | None:
    """(n, planes, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns
    ``cols`` on particles ``p`` at each of the particle's planes (:func:`shape_params_shift`
    there, from the shifts' knots at every plane, :func:`_plane_levels`), or None where the
    calibration has no dimmed refits or the spots no background."""
    if "background" not in cols or "dim0_wx" not in cal.traces.data:
        return None
    table, c_own = _plane_levels(cal)
    n_z = cal.local.z_nm.shape[1]
    at = (p[:, None] * n_z + np.arange(n_z)).ravel()
    c_spot = background_ratio(cols["background"], cols["amplitude"], cal.camera.readnoise)
    c_spot = np.repeat(c_spot, n_z)
    c_from = _correction_start(cal, c_spot, c_own[at], cal.local.z_nm[p].ravel())
    x, x_from = level_positions(table.start[at], c_spot, c_from)
    # where the spot starts at the correction's start, v(x) − v(x_from) is 0 (or NaN: 0 here)
    moved = np.flatnonzero(x != x_from)
    shift = np.zeros((at.size, 3))
    shift[moved] = (level_value(table, x[moved], at[moved])
                    - level_value(table, x_from[moved], at[moved]))  # fmt: skip
    return np.where(np.isfinite(shift), shift, 0.0).reshape(len(p), n_z, 3)


def _shape_params(amplitude: np.ndarray, wx: np.ndarray, wy: np.ndarray,
                  rho: np.ndarray) -> np.ndarray:  # fmt: skip
    """The fitted wx, wy (px), ρ stacked (n, 3): the values whose shifts the joint readout
    takes off."""
    return np.column_stack([wx, wy, rho])


def _plane_levels(cal: CalibrationView) -> tuple[Levels, np.ndarray]:
    """The knots of the wx, wy, ρ shifts (:func:`~latentz.calibration.dimming.shape_levels`)
    and the calibration's own background ratio c at every particle's every plane, row
    ``particle * n_z + plane``; computed once (about 240 bytes per plane: 29 MB for 1000
    particles of 121 planes)."""
    if "plane_levels" not in cal._cache:
        index, stacked = _brightness_traces(cal)
        read = stacked.reshape(-1, stacked.shape[2])

        def trace_at(name: str) -> np.ndarray:
            return read[:, index[name]]

        c_own = background_ratio(trace_at("background"), trace_at("amplitude"),
                                 cal.camera.readnoise)  # fmt: skip
        cal._cache["plane_levels"] = (shape_levels(_shape_params, trace_at, c_own), c_own)
    return cal._cache["plane_levels"]


def _dimming_terms(
    cal: CalibrationView, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray,
    z: np.ndarray,
) -> tuple[Callable[[str], np.ndarray], np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """What the brightness corrections of spots of fitted ``amplitude`` and ``background``
    on particles ``p`` at ``z`` read: particle ``p``'s traces at z (``trace_at(name)``),
    the spots' background ratio c, the particle's own c there, and the c the correction
    starts from (:func:`_correction_start`)."""
    readnoise = cal.camera.readnoise
    index, stacked = _brightness_traces(cal)
    read = interp_rows(cal.local.z_nm, stacked, p, z)  # every trace in one lookup

    def trace_at(name: str) -> np.ndarray:
        return read[:, index[name]]

    c_spot = background_ratio(background, amplitude, readnoise)
    c_own = background_ratio(trace_at("background"), trace_at("amplitude"), readnoise)
    return trace_at, c_spot, c_own, _correction_start(cal, c_spot, c_own, z)


def _correction_start(cal: CalibrationView, c_spot: np.ndarray, c_own: np.ndarray,
                      z: np.ndarray) -> np.ndarray:  # fmt: skip
    """The background ratio c from which the brightness correction of spots of ratio
    ``c_spot`` at ``z`` (nm) starts, their particle's own ratio there ``c_own``.

    Where the calibration particles' brightness follows their size (their heights were
    taken off, :mod:`latentz.calibration.heights`), spots within the calibration's own range
    of brightness at their depth (up to its dimmest particles,
    :func:`~latentz.calibration.dimming.dimmest`) are not shifted; beyond that edge the shift
    starts there, and its start moves back to the particle's own ratio c as the spot's c
    goes as far again (in log c) beyond the edge, so that dim emitters get the whole shift
    from their particle's own fit (:mod:`~latentz.calibration.dimming` notes). Elsewhere it
    starts at ``c_own``."""
    if not cal.options.get("particle_heights", {}).get("applied"):
        return c_own
    if "dimmest" not in cal._cache:
        rows = cal.kept
        c = background_ratio(cal.traces["background"][rows], cal.traces["amplitude"][rows],
                             cal.camera.readnoise)  # fmt: skip
        cal._cache["dimmest"] = dimmest(cal.local.z_nm[rows], c)
    edge = np.fmax(c_own, np.interp(z, *cal._cache["dimmest"]))
    # the start fades from the edge back to the particle's own c as far again beyond it
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.clip(edge**2 / c_spot, c_own, edge)


def _brightness_traces(cal: CalibrationView) -> tuple[dict[str, int], np.ndarray]:
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

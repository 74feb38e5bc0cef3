"""Where :meth:`~latentz.calibration.result.Calibration.apply` puts spots: each spot's nearest
particle, its shape value (or the joint readout's), z from the field model or the particle's
inverse, corrected for the spot's brightness, the checks that keep spots from beyond the
calibrated range out of it, and the lateral correction at that z."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pandas as pd

from latentz._shared.sanity import check_roi_size, check_widths
from latentz._shared.validate import check_choice, check_columns
from latentz.calibration.brightness_shifts import (
    position_shifts,
    shape_params_shift,
    shape_value_shift,
    shift_by_plane,
)
from latentz.calibration.joint_readout import joint_readout, joint_shape
from latentz.calibration.readout import JointZ
from latentz.calibration.shape import shape_value, uses_amplitude
from latentz.calibration.spot_columns import SPOT_COLUMNS, spot_arrays

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["BEYOND_WIDTH", "Z_READOUTS", "Placed", "place", "track_reference", "z_beyond_range"]

#: How :meth:`~latentz.calibration.result.Calibration.apply` reads z from a spot's shape.
Z_READOUTS = ("joint", "shape")
#: A spot whose mean width is more than this many times its particle's curves at its z lies
#: beyond the particle's monotonic range: there the shape value returns to values inside the
#: range while the widths keep growing. The quality verdict's χ² (10 % curve scatter, limit
#: 200) calls such a spot inconsistent too, so single molecules lose nothing more to it.
BEYOND_WIDTH = 2.0
#: Spots searched at once against every plane at their own brightness (:func:`_past_turn`):
#: the shifts' knots and values read take about 30 values per spot and plane, 29 MB for 121
#: planes; 1024 ran 15 % faster than 256 or 4096.
_PLANE_CHUNK = 1024


class Placed(NamedTuple):
    """Where :meth:`~latentz.calibration.result.Calibration.apply` puts spots, and what their
    errors read: the spots' columns ``cols``
    (:func:`~latentz.calibration.spot_columns.spot_arrays`), nearest particles ``p``, shape
    values ``s``, ``z`` (nm, NaN out of range), ``in_range``, the corrected ``x_nm``,
    ``y_nm``, the joint readout (None with the one shape value) and the amplitude reference
    ``ref`` with its relative scatter."""

    cols: dict[str, np.ndarray]
    p: np.ndarray
    s: np.ndarray
    z: np.ndarray
    in_range: np.ndarray
    x_nm: np.ndarray
    y_nm: np.ndarray
    joint: JointZ | None
    ref: np.ndarray
    ref_scatter: float


def place(cal: CalibrationView, spots: pd.DataFrame, amplitude_reference: str,
          z_readout: str) -> Placed:  # fmt: skip
    """Where :meth:`~latentz.calibration.result.Calibration.apply` puts ``spots`` (its checks
    first), before their errors."""
    check_columns("spots", spots, SPOT_COLUMNS)
    check_roi_size(spots.attrs.get("roi_size"), cal.roi_size)
    cols = spot_arrays(spots)
    check_widths(np.column_stack([cols["wx"], cols["wy"]]), cal.width_range_px)
    check_choice("amplitude_reference", amplitude_reference, ("calibration", "particle"))
    check_choice("z_readout", z_readout, Z_READOUTS)
    # a spot with any non-finite fit value is a broken fit: never in range
    located = np.logical_and.reduce([np.isfinite(cols[c]) for c in SPOT_COLUMNS])
    p = cal.nearest(np.where(located, cols["x"], 0.0), np.where(located, cols["y"], 0.0))
    ref, ref_scatter = _amplitude_reference(cal, spots, cols, p, amplitude_reference)
    joint = None
    if z_readout == "joint":
        s, joint = joint_shape(cal, cols, p)
        ref_scatter = 0.0  # z does not use the amplitude
    else:
        s = shape_value(cal.shape, cols["wx"], cols["wy"], cols["rho"], cols["amplitude"],
                        theta=cal.local.theta, amplitude_ref=ref)  # fmt: skip
    z, shifts, in_range = _locate(cal, s, p, cols, located)
    if joint is None and "background" in cols and "dim0_wx" in cal.traces.data:
        s = s - shape_value_shift(cal, cols["amplitude"], cols["background"], p, z, ref)
        z, shifts, in_range = _locate(cal, s, p, cols, located)
    in_range &= ~_beyond_range(cal, cols, p, z)
    if joint is None:
        in_range &= ~_past_turn(cal, cols, p, np.where(in_range, z, np.nan))
    z = np.where(in_range, z, np.nan)
    px = cal.camera.pixel_size_nm
    dimmed = None  # the spot's own brightness moves its fitted centre (coma)
    if "background" in cols and "dim0_dx" in cal.traces.data:
        dimmed = position_shifts(cal, cols["amplitude"], cols["background"], p, z)
    corrected = {}
    for axis, delta in (("x", cal.local.dx), ("y", cal.local.dy)):
        shift = delta[p](np.where(in_range, z, 0.0)) if shifts is None else shifts[axis]
        if dimmed is not None:
            shift = shift + dimmed[axis]
        corrected[axis] = np.where(in_range, (cols[axis] - shift) * px, np.nan)
    return Placed(cols, p, s, z, in_range, corrected["x"], corrected["y"], joint, ref,
                  ref_scatter)  # fmt: skip


def z_beyond_range(cal: CalibrationView, spots: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`~latentz.calibration.result.Calibration.z_beyond_range`: the z (nm) of the
    brightness-corrected joint readout of ``spots`` over all their particle's planes where it
    lies outside that particle's monotonic range (NaN elsewhere), and the particle."""
    cols = spot_arrays(spots)
    located = np.logical_and.reduce([np.isfinite(cols[c]) for c in SPOT_COLUMNS])
    p = cal.nearest(np.where(located, cols["x"], 0.0), np.where(located, cols["y"], 0.0))
    z = joint_shape(cal, cols, p)[1].z_nm
    lo, hi = cal.local.shapes[cal.shape].z_range[p].T
    with np.errstate(invalid="ignore"):
        outside = located & ((z < lo) | (z > hi))
    return np.where(outside, z, np.nan), p


def track_reference(shape: str, spots: pd.DataFrame, cols: dict, theta) -> np.ndarray:
    """A_{ρ=ρ0} of each spot's own track: the amplitude of its spot with the smallest |ρ|
    (or |e_θ| for "auto_A")."""
    base = np.abs(
        shape_value(
            "rho" if shape == "rho_A" else "auto", cols["wx"], cols["wy"], cols["rho"], theta=theta
        )
    )
    if shape == "auto_A":
        base = base / ((np.abs(cols["wx"]) + np.abs(cols["wy"])) / 2)
    frame = pd.DataFrame(
        {"track": spots["particle"].to_numpy(), "base": base, "amplitude": cols["amplitude"]}
    )
    best = frame.loc[frame.groupby("track")["base"].idxmin(), ["track", "amplitude"]]
    lookup = dict(zip(best["track"], best["amplitude"], strict=True))
    return frame["track"].map(lookup).to_numpy(dtype=np.float64)


def _amplitude_reference(
    cal: CalibrationView, spots: pd.DataFrame, cols: dict, p: np.ndarray, amplitude_reference: str
) -> tuple[np.ndarray, float]:
    """Each spot's A_{ρ=ρ0} for the shape value (:meth:`~latentz.calibration.result.
    Calibration.apply`'s ``amplitude_reference``), and the relative scatter of the
    calibration particles' reference about it."""
    shape = cal.shape
    if uses_amplitude(shape) and amplitude_reference == "particle":
        check_columns("spots", spots, ("particle",))
        return track_reference(shape, spots, cols, cal.local.theta), 0.0
    if uses_amplitude(shape):  # the reference about the spot's nearest particle
        return _particle_references(cal)[p], cal.reference_field.scatter
    return cal.local.shapes[shape].amplitude_ref[p], 0.0


def _particle_references(cal: CalibrationView) -> np.ndarray:
    """(n,) :attr:`~latentz.calibration.result.Calibration.reference_field` at every
    particle's position (computed once), so that a spot takes its nearest particle's entry
    instead of a tree query of its own."""
    if "particle_references" not in cal._cache:
        cal._cache["particle_references"] = cal.reference_field(*cal.positions.T)
    return cal._cache["particle_references"]


def _locate(cal: CalibrationView, s: np.ndarray, p: np.ndarray, cols: dict,
            located: np.ndarray) -> tuple:  # fmt: skip
    """z (nm), the field models' Δx', Δy' (px; None for ``nearest``: the particle ``p``'s
    own) and in_range of shape values ``s`` at the spots' positions."""
    if cal.widefield is None:
        z = np.where(located, cal.inverse_z(s, p), np.nan)
        return z, None, np.isfinite(z)
    # field models of z(x', y'; s) and Δx', Δy'(x', y'; z)
    z, dx_w, dy_w, in_range = cal.widefield(
        np.where(located, cols["x"], np.nan),
        np.where(located, cols["y"], np.nan),
        s,
        iterations=cal.options.get("iterations", 0),
    )
    return z, {"x": dx_w, "y": dy_w}, in_range & located


def _beyond_range(cal: CalibrationView, cols: dict, p: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(n,) spots at z (nm) on particles ``p`` whose mean fitted width (``cols``' wx, wy,
    px) exceeds :data:`BEYOND_WIDTH` times the particle's curves at z
    (:meth:`~latentz.calibration.result.Calibration.curves_at`): spots past the end of the
    monotonic range whose shape value mimics one inside it."""
    found = np.isfinite(z)
    out = np.zeros(z.size, dtype=bool)
    if found.any():
        c = cal.curves_at(p[found], z[found])
        width = np.abs(cols["wx"][found]) + np.abs(cols["wy"][found])
        with np.errstate(invalid="ignore"):
            out[found] = width > BEYOND_WIDTH * (np.abs(c["wx"]) + np.abs(c["wy"]))
    return out


def _past_turn(cal: CalibrationView, cols: dict, p: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(n,) spots (columns ``cols``) read at z (nm) from their one shape value whose fitted
    wx, wy, ρ lie nearest their particle's curves outside the monotonic range of its inverse
    z(s): the joint search over all the particle's planes
    (:func:`~latentz.calibration.joint_readout.joint_readout`) puts them beyond it, with each
    plane's curves seen at the spot's brightness there
    (:func:`~latentz.calibration.brightness_shifts.shift_by_plane`) or with the one brightness
    correction at z. Past the range's end the shape value turns back (far from focus a
    high-NA PSF's fitted widths stop growing, or the ROI cuts the spot off), so a spot from
    there has the shape value of one inside it; its widths and ρ together tell the two apart.
    A dim ring's fit takes its core, far narrower than the bright particle's fit at its plane,
    which the correction at each plane shows (full family draw 15: 7 of the 13 spots that the
    one correction leaves in range read over 400 nm off); 4 spots from 1.2 µm below focus on
    draw 2 lie nearest beyond with the one correction alone."""
    out = np.zeros(z.size, dtype=bool)
    found = np.flatnonzero(np.isfinite(z))
    z_range = cal.local.shapes[cal.shape].z_range
    for start in range(0, found.size, _PLANE_CHUNK):
        rows = found[start : start + _PLANE_CHUNK]
        part = {name: values[rows] for name, values in cols.items()}
        lo, hi = z_range[p[rows]].T
        shifts = [shift_by_plane(cal, part, p[rows])]
        if shifts[0] is not None:  # without dimmed refits or background both are None
            shifts.append(shape_params_shift(cal, part, p[rows], z[rows]))
        for shift in shifts:
            joint = joint_readout(cal, part, p[rows], shift, z_only=True)
            with np.errstate(invalid="ignore"):
                out[rows] |= (joint.z_nm < lo) | (joint.z_nm > hi)
    return out

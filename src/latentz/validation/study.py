"""One family member studied with latentz's defaults only: calibrate, localize, score, floor."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd

from latentz.validation.family import FAMILY_SIZES, draw_microscope, family_data
from latentz.validation.floor import oracle_floor
from latentz.validation.truth import coverage_interval, localize_test, score, summary

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration
    from latentz.camera import Camera

__all__ = ["calibrate_defaults", "common_spots", "run_defaults"]


def calibrate_defaults(
    stacks: Any, z_nm: Any, camera: Camera, particle_diameter_nm: float | None = None
) -> tuple[Calibration | None, dict]:
    """``calibrate`` with no shape, ROI or field model given (and the beads' diameter, nm, if
    given): the calibration and what it chose (``ROI``, ``shape``, ``field model``), or None and
    ``fails``, the first line of its error."""
    from latentz.calibration import calibrate

    try:
        cal = calibrate(stacks, z_nm, camera=camera, particle_diameter_nm=particle_diameter_nm)
    except ValueError as err:
        return None, {"fails": str(err).splitlines()[0][:160]}
    return cal, {"ROI": cal.roi_size, "shape": cal.shape, "field model": cal.field_model}


def run_defaults(
    seed: int, size: str = "full", renders: Path | None = None, *, bead_size: bool = False
) -> dict:
    """One row for draw ``seed`` at ``size``: its settings; what ``calibrate`` chose with no
    shape, ROI or field model given (or ``fails``, the first line of its error); the spots
    found and in range; z, x and y RMSE (nm) and the 1σ coverage of each axis over every spot in
    range (:func:`~latentz.validation.truth.summary`) with the 99 % interval that a right error
    model would give it on these spots (``cov x low``, ``cov x high``, …;
    :func:`~latentz.validation.truth.coverage_interval`, the particles' own lateral reference
    shared by each emitter's spots); the oracle floor's RMSEs (nm) over the
    spots in range in both, latentz's z RMSE over those same spots (``z RMSE, floor's spots``)
    and their ratio; seconds taken. ``renders``: a folder that keeps the draw's images
    (:func:`~latentz.validation.family.family_data`). ``bead_size``: give ``calibrate`` the
    draw's bead diameter (``particle_diameter_nm``; nothing for point particles). Beside them,
    the particles' own lateral reference part of σ (``ref x``, ``ref y``, nm) and the 1σ coverage
    of x and y without it (``cov x focus``, ``cov y focus``: ``apply(lateral_reference=
    "focus")`` on the same spots)."""
    start = time.perf_counter()
    draw = draw_microscope(seed, size)
    row = {"seed": seed, "medium": draw.medium, "NA": round(draw.na, 2),
           "px nm": round(draw.pixel_size_nm), "λ nm": round(draw.wavelength_nm),
           "form": draw.form, "astig nm": round(draw.astigmatism_nm),
           "bead nm": round(draw.bead_nm), "z ± nm": round(draw.z_half_nm),
           "step nm": draw.z_step_nm}  # fmt: skip
    data = family_data(draw, renders=renders)
    row["render s"] = round(time.perf_counter() - start)
    diameter_nm = draw.bead_nm if bead_size and draw.bead_nm > 0 else None
    cal, choices = calibrate_defaults(data.stacks, data.z_nm, data.camera, diameter_nm)
    row |= choices
    if cal is None:
        return row
    spots = localize_test(data, calibration=cal)
    scored = score(data, cal.apply(spots))
    errors = summary(scored)
    try:
        floor_rows = common_spots(oracle_floor(data, cal, spots,
                                               patch_px=FAMILY_SIZES[size]["patch_px"]),
                                  scored)  # fmt: skip
        floor = summary(floor_rows)
        same = summary(scored.merge(in_range_keys(floor_rows), on=["emitter", "frame"]))
    except ValueError as err:  # the floor's own calibration failed: no floor for this draw
        floor = same = {f"rmse_{axis}": float("nan") for axis in "xyz"} | {"spots": 0.0}
        row["floor fails"] = str(err).splitlines()[0][:160]
    row |= {"spots": int(errors["spots"]), "in range": round(errors["in_range"], 2),
            "z RMSE": errors["rmse_z"], "z RMSE, floor's spots": same["rmse_z"],
            "floor": floor["rmse_z"], "ratio": same["rmse_z"] / floor["rmse_z"],
            "floor spots": int(floor["spots"]),
            "x RMSE": errors["rmse_x"], "y RMSE": errors["rmse_y"], "floor x": floor["rmse_x"],
            "floor y": floor["rmse_y"], "cov x": errors["cover_x"], "cov y": errors["cover_y"],
            "cov z": errors["cover_z"], "fails": ""}  # fmt: skip
    for axis in "xyz":
        shared = cal.reference_sigma_nm(axis) if axis in "xy" else 0.0
        row[f"cov {axis} low"], row[f"cov {axis} high"] = coverage_interval(scored, axis, shared)
    focus = summary(score(data, cal.apply(spots, lateral_reference="focus")))
    for axis in "xy":
        row[f"ref {axis}"] = cal.reference_sigma_nm(axis)
        row[f"cov {axis} focus"] = focus[f"cover_{axis}"]
    row["total s"] = round(time.perf_counter() - start)
    return row


def common_spots(floor: pd.DataFrame, scored: pd.DataFrame) -> pd.DataFrame:
    """The floor's rows restricted to the spots that the calibration under test put in range
    (the floor's own in-range flag kept), so that both RMSEs are over the same spots."""
    return floor.merge(in_range_keys(scored), on=["emitter", "frame"])


def in_range_keys(scored: pd.DataFrame) -> pd.DataFrame:
    """The (emitter, frame) keys of a scored table's spots in range."""
    return scored.loc[scored["in_range"].to_numpy(bool), ["emitter", "frame"]]

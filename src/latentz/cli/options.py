"""Shared option parsing for the CLI: camera, z positions, output formats.

Kept apart from the commands (``main.py``) so that each piece is testable as a plain function.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from latentz._shared.validate import check_finite, check_int, check_positive
from latentz.camera import Camera
from latentz.camera.model import poisson_equivalent

__all__ = ["camera_from_options", "read_camera_file", "stage_offsets_px", "z_positions"]


def camera_from_options(
    camera_file: str | os.PathLike | None,
    *,
    offset: float | None = None,
    gain: float | None = None,
    readnoise: float | None = None,
    pixel_size_nm: float | None = None,
    emccd: bool = False,
    base: Camera | None = None,
) -> Camera | None:
    """A Camera from a JSON file and/or explicit values (explicit values win); None if neither.

    The JSON file holds ``offset``, ``gain``, ``readnoise``, ``pixel_size_nm`` and optionally
    ``flatfield``: a path to a TIFF image, relative to the JSON file. With ``emccd``, the gain
    and read noise given (file or values) are an EMCCD's datasheet values, made
    Poisson-equivalent (:func:`latentz.camera.model.poisson_equivalent`). With ``base``, what
    is not given keeps ``base``'s value (and the result is ``base`` if nothing is given).
    """
    values: dict = {}
    flatfield = None
    if base is not None:
        values = {k: v for k, v in base.as_dict().items() if k != "flatfield"}
        flatfield = base.flatfield
    given: dict = {}
    if camera_file is not None:
        from_file, from_file_flat = read_camera_file(camera_file)
        given.update(from_file)
        flatfield = from_file_flat if from_file_flat is not None else flatfield
    options = {
        "offset": offset,
        "gain": gain,
        "readnoise": readnoise,
        "pixel_size_nm": pixel_size_nm,
    }
    given.update({k: v for k, v in options.items() if v is not None})
    values.update(poisson_equivalent(given, emccd))
    if not values and flatfield is None:
        return None
    return Camera(**values, flatfield=flatfield)


def read_camera_file(camera_file: str | os.PathLike) -> tuple[dict, np.ndarray | None]:
    """The values a camera JSON file gives (``offset``, ``gain``, ``readnoise``,
    ``pixel_size_nm``), and its flatfield image (or None)."""
    path = Path(camera_file)
    if not path.exists():
        raise FileNotFoundError(f"No such camera file: {path}")
    try:
        from_file = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"Camera file {path.name} is not valid JSON: {exc}") from exc
    if not isinstance(from_file, dict):
        raise ValueError(f"Camera file {path.name} must hold a JSON object.")
    unknown = set(from_file) - {"offset", "gain", "readnoise", "pixel_size_nm", "flatfield"}
    if unknown:
        raise ValueError(f"Camera file {path.name} has unknown key(s): {sorted(unknown)}.")
    flatfield = None
    if "flatfield" in from_file:
        import tifffile

        flatfield = tifffile.imread(path.parent / from_file.pop("flatfield"))
    return from_file, flatfield


def _numbers(path: str | os.PathLike, *, what: str, form: str, ndmin: int) -> np.ndarray:
    """Numbers from a text file (comma-separated, ``#`` comments), with errors naming ``what``."""
    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"No such {what}: {source}")
    try:
        values = np.loadtxt(source, dtype=np.float64, delimiter=",", ndmin=ndmin, comments="#")
    except ValueError as exc:
        raise ValueError(f"The {what} {source.name} must hold {form}: {exc}") from exc
    if values.ndim != ndmin:
        raise ValueError(f"The {what} {source.name} must hold {form}.")
    return values


def z_positions(
    n_planes: int,
    *,
    z_start_nm: float | None = None,
    z_step_nm: float | None = None,
    z_file: str | os.PathLike | None = None,
) -> np.ndarray:
    """Piezo z (nm) of each plane: from ``--z-start``/``--z-step`` or a text file, one per line."""
    n_planes = check_int("n_planes", n_planes, minimum=1)
    if z_file is not None:
        if z_start_nm is not None or z_step_nm is not None:
            raise ValueError("Give either --z-file or --z-start/--z-step, not both.")
        z = _numbers(z_file, what="z file", form="one number per line", ndmin=1)
    else:
        if z_start_nm is None or z_step_nm is None:
            raise ValueError("Give the plane positions with --z-start and --z-step, or --z-file.")
        start = check_finite("z_start_nm", z_start_nm)
        step = check_positive("z_step_nm", z_step_nm)
        z = start + step * np.arange(n_planes)
    if z.size != n_planes:
        raise ValueError(f"The stack has {n_planes} planes but {z.size} z positions were given.")
    return z


def stage_offsets_px(path: str | os.PathLike, n_stacks: int) -> np.ndarray:
    """(x, y) field position of each stack's pixel [0, 0] (pixels), from a CSV row per stack."""
    source = Path(path)
    offsets = _numbers(source, what="stage-offset file", form="'x,y' rows", ndmin=2)
    if offsets.shape != (n_stacks, 2) or not np.all(np.isfinite(offsets)):
        raise ValueError(
            f"The stage-offset file {source.name} must hold {n_stacks} finite 'x,y' rows "
            f"(one per stack), got shape {offsets.shape}."
        )
    return offsets

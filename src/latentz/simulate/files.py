"""Writing simulated datasets to a folder: TIFF stacks, ground-truth CSV, metadata JSON, PNG."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.atomic import atomic_path, write_text_atomic

__all__ = ["write_files", "dataset_metadata"]


def _write_tiff(path: Path, array: np.ndarray) -> Path:
    import tifffile

    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, array, photometric="minisblack", metadata={"axes": "ZYX"})
    return path


def _write_csv(path: Path, table: pd.DataFrame) -> Path:
    with atomic_path(path) as tmp:
        table.to_csv(tmp, index=False)
    return path


def _write_json(path: Path, data: dict[str, Any]) -> Path:
    write_text_atomic(path, json.dumps(data, indent=2, default=_jsonable) + "\n")
    return path


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"Cannot write {type(value).__name__} to JSON.")


def write_files(dataset: Any, out_dir: str | os.PathLike) -> list[Path]:
    """Write a dataset object (calibration, gear or apertures) to ``out_dir``.

    Files: ``<kind>_*.tif`` (uint16 stacks or movies), ``<kind>_truth.csv`` (and
    ``gear_motion.csv`` for the gear), ``<kind>_z_nm.txt`` (one piezo position per plane, for
    calibration stacks) and ``<kind>_metadata.json``. Every file is written atomically.
    """
    out = Path(out_dir)
    meta = dataset.metadata()
    kind = meta["kind"]
    written: list[Path] = []
    if kind == "calibration":
        names = []
        for k, stack in enumerate(dataset.stacks):
            path = _write_tiff(out / f"calibration_stack_{k:02d}.tif", stack)
            names.append(path.name)
            written.append(path)
        meta["files"] = {"stacks": names}
        written.append(_write_csv(out / "calibration_truth.csv", dataset.truth))
        z_text = "".join(f"{z:.6g}\n" for z in dataset.z_nm)
        path = out / "calibration_z_nm.txt"
        write_text_atomic(path, z_text)
        written.append(path)
    elif kind == "apertures":
        written.append(_write_tiff(out / "apertures.tif", dataset.frames))
        written.append(_write_csv(out / "apertures_truth.csv", dataset.truth))
    elif kind == "gear":
        written.append(_write_tiff(out / "gear_movie.tif", dataset.frames))
        written.append(_write_csv(out / "gear_truth.csv", dataset.truth))
        written.append(_write_csv(out / "gear_motion.csv", dataset.motion))
    else:  # pragma: no cover - metadata kinds are fixed by the dataset classes
        raise ValueError(f"Unknown dataset kind {kind!r}.")
    written.append(_write_json(out / f"{kind}_metadata.json", meta))
    return written


def dataset_metadata(obj: Any) -> dict[str, Any]:
    """A dataset's camera, optics, aberrations, seed and conventions, for its metadata JSON."""
    return {
        "camera": obj.camera.as_dict(),
        "optics": obj.optics.as_dict(),
        "aberrations": obj.aberrations.as_dict(),
        "seed": obj.seed,
        "conventions": {
            "image": "x is the column, y the row; the centre of pixel [i, j] is at x = j, y = i",
            "axial": "defocus_nm = z_nm + z_piezo_nm; z_focus_nm = focus_defocus_nm - z_nm",
            "intensity": "photons are photoelectrons; ADU = electrons / gain + offset",
        },
    }

"""Writing simulated datasets to a folder: TIFF stacks, ground-truth CSV, metadata JSON, PNG."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.atomic import atomic_path, write_text_atomic
from latentz._shared.validate import check_choice

__all__ = ["write_dataset", "write_files", "DATASET_KINDS"]

DATASET_KINDS = ("calibration", "gear", "apertures")


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


def write_dataset(
    kind: str,
    out_dir: str | os.PathLike,
    *,
    seed: int = 0,
    quick: bool = False,
    plot: bool = False,
) -> list[Path]:
    """Simulate a dataset of ``kind`` ('calibration', 'gear' or 'apertures') and write it.

    ``quick`` makes a small dataset in a few seconds; ``plot`` also writes ``psf_gallery.png``.
    Returns the paths written. The CLI's ``latentz simulate KIND --out DIR`` calls this.
    """
    from latentz.simulate.datasets import aperture_array, calibration_dataset
    from latentz.simulate.figures import save_psf_gallery

    check_choice("kind", kind, DATASET_KINDS)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise TypeError(f"Expected `seed` to be an integer, got {seed!r}.")
    if kind == "calibration":
        if quick:
            dataset = calibration_dataset(
                n_particles=16,
                z_nm=np.linspace(-2000.0, 2000.0, 21),
                n_stage_positions=4,
                frame_shape=(128, 128),
                min_spacing_px=30.0,
                defective_fraction=0.125,
                seed=seed,
            )
        else:
            dataset = calibration_dataset(defective_fraction=0.05, seed=seed)
    elif kind == "apertures":
        dataset = aperture_array(shape=(128, 128) if quick else (512, 512), seed=seed)
    else:
        from latentz.simulate.gear import gear_movie

        dataset = gear_movie(quick=quick, seed=seed)
    written = write_files(dataset, out_dir)
    if plot:
        path = Path(out_dir) / "psf_gallery.png"
        save_psf_gallery(path, optics=dataset.optics, aberrations=dataset.aberrations)
        written.append(path)
    return written

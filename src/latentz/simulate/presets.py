"""Dataset presets: the calibration stacks, the gear movie and the aperture array that
``latentz simulate KIND`` and the demo write, full-size or quick."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from latentz._shared.validate import check_choice
from latentz.simulate.datasets import aperture_array, calibration_dataset
from latentz.simulate.figures import save_psf_gallery
from latentz.simulate.files import write_files
from latentz.simulate.gear import gear_movie

__all__ = ["DATASET_KINDS", "write_dataset"]

DATASET_KINDS = ("calibration", "gear", "apertures")


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
        dataset = gear_movie(quick=quick, seed=seed)
    written = write_files(dataset, out_dir)
    if plot:
        path = Path(out_dir) / "psf_gallery.png"
        save_psf_gallery(path, optics=dataset.optics, aberrations=dataset.aberrations)
        written.append(path)
    return written

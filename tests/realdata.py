"""Loaders for the real stacks in ../shared/data, shared by the pipeline tests."""

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
#: fit3Dcspline bead: offset 400 ADU, 0.1 e-/ADU (data README); pixel size not recorded.
FIT3D_CAMERA = {"offset": 400.0, "gain": 0.1, "readnoise": 1.0, "pixel_size_nm": 100.0}
#: SMLM 2016 AS beads: 100 nm pixels, ~100 ADU baseline, ~0.16 e-/ADU (30,000-photon beads).
SMLM_CAMERA = {"offset": 100.0, "gain": 0.16, "readnoise": 1.0, "pixel_size_nm": 100.0}


def need(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"real data {name} not found in {DATA} (shared data folder absent)")
    return path


def fit3d_bead() -> tuple[np.ndarray, np.ndarray]:
    """(201, 21, 21) ADU stack and its piezo z (nm, 10 nm steps, plane 100 at 0)."""
    import tifffile

    stack = tifffile.imread(need("fit3dcspline-bead.tif")).astype(np.float64)
    return stack, (np.arange(stack.shape[0]) - 100) * 10.0


def smlm_beads() -> tuple[np.ndarray, np.ndarray]:
    """(151, 150, 150) ADU stack and its z (nm, −750..750)."""
    import tifffile

    stack = tifffile.imread(need("smlm2016-as-beads.tif")).astype(np.float64)
    return stack, np.linspace(-750.0, 750.0, stack.shape[0])

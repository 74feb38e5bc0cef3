"""Loaders for the real stacks in ../shared/data (or ``$LATENTZ_SHARED/data``), and the score
of localized z against their outside truth, shared by the real-data tests."""

import os
from pathlib import Path

import numpy as np
import pytest

DATA = (
    Path(os.environ.get("LATENTZ_SHARED", Path(__file__).resolve().parents[1] / ".." / "shared"))
    / "data"
)
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


def score_z(found_nm, true_nm, group=None) -> dict[str, float]:
    """Localized z against an outside truth (piezo or simulated z, nm) whose origin differs from
    the calibration's by one constant: z = 0 is the calibration particles' focus there.

    ``offset``: that constant, the mean error. ``rms``: the RMS error about it. ``jitter``: the
    measured precision, from the errors of neighbouring planes (sorted by true z, within each
    ``group``): the truth steps by a known amount, so the change of the error from one plane to
    the next is noise; its standard deviation over √2. ``slope``: of found against true z, with
    its standard error ``slope_se`` (residuals of RMS ``rms``).
    """
    found, true = np.asarray(found_nm, float), np.asarray(true_nm, float)
    group = np.zeros(true.size) if group is None else np.asarray(group)
    order = np.lexsort((true, group))
    error, group = (found - true)[order], group[order]
    offset = float(np.mean(error))
    rms = float(np.sqrt(np.mean((error - offset) ** 2)))
    step = np.diff(error)[group[1:] == group[:-1]]
    slope = float(np.polyfit(true, found, 1)[0])
    return {
        "offset": offset,
        "rms": rms,
        "jitter": float(np.std(step) / np.sqrt(2)),
        "slope": slope,
        "slope_se": rms / (np.sqrt(true.size) * float(np.std(true))),
        "n": int(true.size),
    }

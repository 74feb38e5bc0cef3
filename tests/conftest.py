"""Fixtures shared across test folders: a small simulated microscope written as files."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import tifffile

SMALL_FIELD = (384, 384)


@dataclass(frozen=True)
class SmallMicroscope:
    """One calibration stack and a short rotating-gear movie of the same simulated microscope."""

    folder: Path
    calibration: object  # latentz.simulate.CalibrationDataset
    gear: object  # latentz.simulate.GearMovie


@pytest.fixture(scope="session")
def small_microscope(tmp_path_factory) -> SmallMicroscope:
    from latentz import simulate as sim

    folder = tmp_path_factory.mktemp("small_microscope")
    aberrations = sim.AberrationMap.default(seed=2, field_shape=SMALL_FIELD)
    data = sim.calibration_dataset(
        n_particles=40,
        z_nm=np.linspace(-1500, 1500, 31),
        n_stage_positions=1,
        frame_shape=SMALL_FIELD,
        min_spacing_px=40.0,
        aberrations=aberrations,
        seed=2,
    )
    tifffile.imwrite(folder / "stack.tif", data.stacks[0])
    np.savetxt(folder / "z.txt", data.z_nm)
    gear = sim.gear_movie(
        n_cycles=5,
        n_particles=8,
        gear_diameter_um=36.0,
        frame_shape=SMALL_FIELD,
        aberrations=aberrations,
        seed=2,
    )
    tifffile.imwrite(folder / "movie.tif", gear.frames)
    return SmallMicroscope(folder, data, gear)


@pytest.fixture(scope="session")
def small_calibration(small_microscope):
    """The small microscope's calibration with the nearest particle's models, made once for the
    tests that only apply it (treat it as read-only)."""
    from latentz.calibration import calibrate

    data = small_microscope.calibration
    return calibrate(list(data.stacks), data.z_nm, camera=data.camera, field_model="nearest")


@pytest.fixture(scope="session")
def small_zernike_calibration(small_microscope):
    """The small microscope's calibration with the Zernike field model, made once (read-only)."""
    from latentz.calibration import calibrate

    data = small_microscope.calibration
    return calibrate(list(data.stacks), data.z_nm, camera=data.camera, field_model="zernike")

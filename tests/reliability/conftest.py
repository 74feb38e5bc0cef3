"""Hypothesis profile for the reliability tests: bounded examples, no per-example deadline (numba
compiles on first call), derandomized so CI is reproducible; and a calibration file of the small
simulated microscope for the CLI tests."""

import pytest
from hypothesis import settings

settings.register_profile("reliability", max_examples=60, deadline=None, derandomize=True)
settings.load_profile("reliability")


@pytest.fixture(scope="session")
def calibration_file(small_microscope, tmp_path_factory):
    """The small microscope's calibration (nearest-particle models), saved to HDF5."""
    from latentz.calibration import calibrate

    data = small_microscope.calibration
    path = tmp_path_factory.mktemp("calibration") / "cal.h5"
    calibrate(list(data.stacks), data.z_nm, camera=data.camera, field_model="nearest").save(path)
    return path

"""A calibration of the small simulated microscope, shared by the pipeline tests."""

import pytest


@pytest.fixture(scope="session")
def small_calibration(small_microscope):
    import latentz as lz

    data = small_microscope.calibration
    return lz.calibrate(data.stacks[0], data.z_nm, camera=data.camera, field_model="nearest")

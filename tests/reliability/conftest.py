"""Hypothesis profile for the reliability tests: bounded examples, no per-example deadline (numba
compiles on first call), derandomized so CI is reproducible; and a calibration file of the small
simulated microscope for the CLI tests."""

import pytest
from hypothesis import settings

settings.register_profile("reliability", max_examples=60, deadline=None, derandomize=True)
settings.load_profile("reliability")


@pytest.fixture(scope="session")
def calibration_file(small_calibration, tmp_path_factory):
    """The small microscope's calibration (nearest-particle models), saved to HDF5."""
    path = tmp_path_factory.mktemp("calibration") / "cal.h5"
    small_calibration.save(path)
    return path

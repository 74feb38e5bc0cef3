"""The public names of latentz.calibration import."""

import latentz.calibration as calibrate_package


def test_all_names_import():
    for name in calibrate_package.__all__:
        assert getattr(calibrate_package, name) is not None, name

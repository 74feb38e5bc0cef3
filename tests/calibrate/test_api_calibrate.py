"""The public names of latentz.calibrate import."""

import latentz.calibrate as calibrate_package


def test_all_names_import():
    for name in calibrate_package.__all__:
        assert getattr(calibrate_package, name) is not None, name

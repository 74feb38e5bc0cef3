"""The motion subpackage's public names all import."""

import latentz.motion as motion


def test_all_names_import():
    for name in motion.__all__:
        assert getattr(motion, name) is not None, name
    assert {"link", "rigid_motion", "motion_uncertainty"} <= set(motion.__all__)

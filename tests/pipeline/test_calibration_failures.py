"""A calibration where every particle fails says so, with the reasons, instead of failing
later with "zero-size array"; its `apply` is never reached."""

import numpy as np
import pytest

import latentz as lz


def test_every_particle_failing_is_one_clear_error():
    # a "particle" placed on pure background: no spot to fit, no focus
    rng = np.random.default_rng(0)
    stack = 100 + rng.poisson(5, (40, 32, 32)).astype(float)
    with pytest.raises(ValueError, match=r"Every one of the 1 calibration particles failed") as e:
        lz.calibrate(
            stack, np.arange(40) * 50.0, camera=lz.Camera(offset=90), positions=[[(16, 16)]]
        )
    assert "never_in_focus: 1" in str(e.value) and "roi_size=None" in str(e.value)

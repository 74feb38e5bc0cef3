"""The brightness shift at every plane of a spot's particle
(:func:`latentz.calibration.brightness_shifts.shift_by_plane`), read from knots computed once per
calibration, is the shift at one z read at each plane."""

import dataclasses

import numpy as np
import pytest

from latentz.calibration.brightness_shifts import shape_params_shift, shift_by_plane


@pytest.mark.parametrize("heights", [False, True])
def test_the_shift_at_every_plane_is_the_shift_read_at_each(small_calibration, heights):
    options = small_calibration.options | {"particle_heights": {"applied": heights}}
    cal = dataclasses.replace(small_calibration, options=options, _cache={})
    assert "dim0_wx" in cal.traces.data
    rng = np.random.default_rng(0)
    n, n_z = 40, cal.local.z_nm.shape[1]
    p = rng.integers(0, len(cal.positions), n)
    # from brighter than the particles to 100 times dimmer: many planes need no shift
    cols = {"amplitude": 10 ** rng.uniform(1, 4, n), "background": rng.uniform(5, 50, n)}
    by_plane = shift_by_plane(cal, cols, p)
    each = shape_params_shift(cal, {k: np.repeat(v, n_z) for k, v in cols.items()},
                              np.repeat(p, n_z), cal.local.z_nm[p].ravel())  # fmt: skip
    assert np.any(by_plane != 0) and np.any(by_plane == 0)
    np.testing.assert_allclose(by_plane, each.reshape(n, n_z, 3), rtol=1e-9, atol=1e-12)

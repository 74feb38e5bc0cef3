"""The yardstick :func:`latentz.validation.bounds.curves_fit_z` against known truth: spots drawn
from its own model (the Gaussian of eq. 1 with a calibration particle's curves at a chosen z)
are fitted back to that z with the spread of the Cramér–Rao bound."""

import numpy as np
import pytest

from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.fit import render_rois
from latentz.simulate.molecules import random_microscope
from latentz.validation.bounds import curves_fit_z, localization_bounds
from latentz.validation.molecules import bead_calibration

pytestmark = pytest.mark.slow  # one bead calibration (~10 s with numba compiling)


def test_curves_fit_z_reaches_the_bound_when_its_model_is_the_truth():
    rng = np.random.default_rng(7)
    calibration = bead_calibration(random_microscope(rng), 7)
    size, photons, background = calibration.roi_size, 5000.0, 20.0
    z_true = np.repeat([-300.0, -100.0, 100.0, 300.0], 25)
    particle = np.zeros(len(z_true), int)
    curves = calibration.curves_at(particle, z_true)
    wx, wy, rho = (curves[c] for c in ("wx", "wy", "rho"))
    amplitude = photons / (2 * np.pi * wx * wy * np.sqrt(1 - rho**2))
    shift = shape_params_shift(calibration, {"amplitude": amplitude,
                                             "background": np.full_like(z_true, background)},
                               particle, z_true)  # fmt: skip
    shift = np.zeros((len(z_true), 3)) if shift is None else shift
    centre = (size - 1) / 2 + rng.uniform(-0.5, 0.5, (len(z_true), 2))
    params = np.column_stack([centre, amplitude, np.full_like(z_true, background),
                              wx + shift[:, 0], wy + shift[:, 1], rho + shift[:, 2]])  # fmt: skip
    readnoise = calibration.camera.readnoise
    rois = rng.poisson(render_rois(params, shape=size)) + rng.normal(
        0, readnoise, (len(z_true), size, size)
    )
    # a start 150 nm off on either side, as a readout's first guess may be
    start = np.column_stack([np.full_like(centre, (size - 1) / 2), amplitude,
                             np.full_like(z_true, background), np.full_like(z_true, photons),
                             z_true + rng.choice([-150.0, 150.0], len(z_true))])  # fmt: skip
    z = curves_fit_z(calibration, rois, particle, start)
    bound = localization_bounds(calibration, particle, z_true, np.full_like(z_true, photons),
                                background, readnoise=readnoise)[:, 2]  # fmt: skip
    ratio = (z - z_true) / bound
    assert np.all(np.isfinite(ratio))
    # an efficient estimator: mean square of error / bound near 1 (1.37 here: the curves are
    # interpolated between planes 25 nm apart, and their slope, which the bound takes over
    # ±10 nm, changes from one interval to the next; a fit that missed the z by the start's
    # 150 nm would give about 400), and no bias beyond 3 standard errors
    assert 0.6 <= np.mean(ratio**2) <= 1.5, np.mean(ratio**2)
    assert abs(np.mean(ratio)) <= 3 / np.sqrt(len(ratio))

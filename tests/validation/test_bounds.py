"""The yardstick :func:`latentz.validation.bounds.curves_fit_z` against known truth: spots drawn
from its own model (the Gaussian of eq. 1 with a calibration particle's curves at a chosen z)
are fitted back to that z with the spread of the Cramér–Rao bound. The physical bounds of
:func:`latentz.validation.bounds.psf_bounds` against the symmetries of the PSF."""

import numpy as np
import pytest

from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.camera import Camera
from latentz.fit import render_rois
from latentz.simulate import AberrationMap, Optics
from latentz.simulate.molecules import Microscope, random_microscope
from latentz.validation.bounds import curves_fit_z, localization_bounds, psf_bounds
from latentz.validation.molecules import bead_calibration


@pytest.mark.slow  # one bead calibration (~10 s with numba compiling)
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
    # an efficient estimator: mean square of error / bound near 1 (1.37 here, perhaps because
    # the curves, interpolated between planes 25 nm apart, change slope from one interval to
    # the next, which the bound's ±10 nm difference need not see; a fit that kept the start's
    # 150 nm error would give several hundred), and no bias beyond 3 standard errors
    assert 0.6 <= np.mean(ratio**2) <= 1.5, np.mean(ratio**2)
    assert abs(np.mean(ratio)) <= 3 / np.sqrt(len(ratio))


def _microscope(aberrations_nm: dict[int, float], readnoise: float = 0.0) -> Microscope:
    optics = Optics(na=1.4, immersion_index=1.515, wavelength_nm=600.0, magnification=65.0,
                    camera_pixel_um=6.5)  # fmt: skip
    camera = Camera(offset=100.0, gain=1.0, readnoise=readnoise, pixel_size_nm=100.0)
    return Microscope(optics, AberrationMap.constant(aberrations_nm), camera)


def test_psf_bounds_follow_the_symmetries_of_an_aberration_free_psf():
    """Without aberrations the PSF is round and the same above and below focus: x and y are
    known alike, z as well at +z as at -z, and at focus, where the image does not change to
    first order with z, hardly at all."""
    microscope = _microscope({4: 0.0})
    z = np.array([-400.0, 0.0, 400.0])
    bounds = psf_bounds(microscope, np.full(3, 40.5), np.full(3, 40.5), z, np.full(3, 2000.0),
                        10.0, size=15)  # fmt: skip
    # the simulator samples x and y alike to 0.6 % at focus, where the spot is sharpest
    np.testing.assert_allclose(bounds[:, 0], bounds[:, 1], rtol=0.01)
    np.testing.assert_allclose(bounds[0, 2], bounds[2, 2], rtol=0.02)
    assert bounds[1, 2] > 5 * bounds[0, 2]
    assert bounds[1, 0] < bounds[0, 0]  # the in-focus spot is the sharper


def test_psf_bounds_fall_as_one_over_root_photons_without_background():
    microscope = _microscope({5: 60.0, 11: 10.0})
    photons = np.array([100.0, 10000.0])
    bounds = psf_bounds(microscope, np.full(2, 30.3), np.full(2, 31.7), np.full(2, 150.0),
                        photons, 0.0, size=15)  # fmt: skip
    np.testing.assert_allclose(bounds[0] / bounds[1], 10.0, rtol=1e-6)


def test_astigmatism_makes_z_known_at_focus():
    """Astigmatism breaks the symmetry about focus, so z is measurable there: its bound falls
    far below the aberration-free one."""
    args = (np.array([40.5]), np.array([40.5]), np.array([0.0]), np.array([2000.0]), 10.0)
    round_z = psf_bounds(_microscope({4: 0.0}), *args, size=15)[0, 2]
    astigmatic_z = psf_bounds(_microscope({5: 70.0}), *args, size=15)[0, 2]
    assert astigmatic_z < round_z / 5

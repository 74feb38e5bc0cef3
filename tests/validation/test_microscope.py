"""The validation microscope's optics against analytic cases (independent of latentz.simulate)."""

import numpy as np
import pytest
from scipy.special import j0, j1

from latentz.validation import AberrationFields, Microscope, bead_slices, make_data

MICROSCOPE = Microscope()


def test_in_focus_unaberrated_image_is_the_airy_disk():
    r = np.linspace(1.0, 2000.0, 80)
    field = MICROSCOPE.amplitude(r, np.zeros(1), MICROSCOPE.wavefront_nm({}), np.zeros(1))
    intensity = np.abs(field[0, 0]) ** 2
    v = 2 * np.pi * MICROSCOPE.na * r / MICROSCOPE.wavelength_nm
    airy = (2 * j1(v) / v) ** 2
    # the peak's absolute value is the pupil area (Parseval), so one photon integrates to 1
    centre = MICROSCOPE.amplitude(np.zeros(1), np.zeros(1), MICROSCOPE.wavefront_nm({}), [0.0])
    assert abs(centre[0, 0, 0]) ** 2 == pytest.approx(MICROSCOPE.pupil_area**2, rel=1e-5)
    np.testing.assert_allclose(intensity / abs(centre[0, 0, 0]) ** 2, airy, atol=1e-5)


def test_pixel_image_holds_the_airy_encircled_energy():
    image = MICROSCOPE.pixel_image(0.0, 0.0, MICROSCOPE.wavefront_nm({}), [0.0], 41)
    # the square patch holds more than its inscribed disk and less than its circumscribed one;
    # the Airy disk's encircled energy is 1 - J0(v)^2 - J1(v)^2
    half = 20.5 * MICROSCOPE.pixel_size_nm
    v = 2 * np.pi * MICROSCOPE.na / MICROSCOPE.wavelength_nm * np.array([half, half * np.sqrt(2)])
    inner, outer = 1 - j0(v) ** 2 - j1(v) ** 2
    assert inner < image.sum() < outer


def test_defocus_is_symmetric_without_aberrations():
    wave = MICROSCOPE.wavefront_nm({})
    plus, minus = MICROSCOPE.pixel_image(0.0, 0.0, wave, [1200.0, -1200.0], 21)
    np.testing.assert_allclose(plus, minus, atol=1e-6 * plus.max())


def test_astigmatism_turns_the_image_by_90_degrees_through_focus():
    wave = MICROSCOPE.wavefront_nm({"astig_vertical": 60.0})
    plus, minus = MICROSCOPE.pixel_image(0.0, 0.0, wave, [800.0, -800.0], 21)
    np.testing.assert_allclose(plus, np.rot90(minus), atol=1e-5 * plus.max())
    assert np.abs(plus - minus).max() > 0.1 * plus.max()  # and the image is not round


def test_pupil_quadrature_has_converged():
    wave = {"astig_oblique": 65.0, "coma_x": 20.0, "spherical": 10.0}
    fine = Microscope(radial_nodes=40, azimuth_nodes=80)
    args = (0.2, -0.4)
    a = MICROSCOPE.pixel_image(*args, MICROSCOPE.wavefront_nm(wave), [-3000.0, 3000.0], 31)
    b = fine.pixel_image(*args, fine.wavefront_nm(wave), [-3000.0, 3000.0], 31)
    np.testing.assert_allclose(a, b, atol=1e-4 * b.max())


def test_bead_slices_integrate_the_sphere_cross_section():
    offsets, weights = bead_slices(200.0)
    t = offsets / 100.0
    for k in (0, 2, 4):  # exact moments of (1 - t^2) over [-1, 1], normalised
        exact = (2 / (k + 1) - 2 / (k + 3)) / (4 / 3)
        assert np.sum(weights * t**k) == pytest.approx(exact)


def test_fields_are_not_low_order_polynomials():
    fields = AberrationFields.random((128, 128), seed=3)
    yy, xx = np.mgrid[0:128, 0:128] / 127.0
    design = np.stack([xx**i * yy**j for i in range(4) for j in range(4 - i)], axis=-1)
    design = design.reshape(-1, design.shape[-1])
    for m in fields.maps:
        values = m.ravel()
        resid = values - design @ np.linalg.lstsq(design, values, rcond=None)[0]
        assert resid.std() > 0.15 * values.std()  # a cubic leaves a good part unexplained


@pytest.mark.slow
def test_small_study_images_and_truth():
    data = make_data("small", seed=2)
    cal, test = data.calibration_truth, data.test_truth
    assert len(data.stacks) == 2 and data.stacks[0].shape == (data.z_nm.size, 128, 128)
    # test emitters are never calibration particles: at least a few pixels away from all
    d = np.hypot(test["x"].to_numpy()[:, None] - cal["x"].to_numpy(),
                 test["y"].to_numpy()[:, None] - cal["y"].to_numpy())  # fmt: skip
    assert d.min() > 3.0
    # mean ADU above the offset matches the photons rendered (gain 0.5 e-/ADU)
    expected = data.expected[0].sum()
    adu = (data.stacks[0] - data.camera.offset).sum() * data.camera.gain
    assert adu == pytest.approx(expected, rel=1e-3)


@pytest.mark.parametrize(("kwargs", "match"), [({"size": "huge"}, "size"),
                                               ({"n_frames": 0}, "n_frames")])  # fmt: skip
def test_make_data_refuses_bad_input_before_work(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_data(**kwargs)

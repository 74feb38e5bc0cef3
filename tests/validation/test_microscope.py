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
    offsets, discs, weights = bead_slices(200.0)
    t = offsets / 100.0
    for k in (0, 2, 4):  # exact moments of (1 - t^2) over [-1, 1], normalised
        exact = (2 / (k + 1) - 2 / (k + 3)) / (4 / 3)
        assert np.sum(weights * t**k) == pytest.approx(exact)
    np.testing.assert_allclose(offsets**2 + discs**2, 100.0**2)  # each disc lies on the sphere
    # a uniform ball of radius R projects to a lateral variance R^2 / 5 per axis
    assert np.sum(weights * discs**2 / 4) == pytest.approx(100.0**2 / 5)


@pytest.mark.parametrize(("na", "n_medium", "pixel_nm", "radius_nm"),
                         [(1.4, 1.518, 100.0, 100.0), (0.8, 1.0, 65.0, 100.0)])  # fmt: skip
def test_disc_image_is_the_mean_of_point_images_over_the_disc(na, n_medium, pixel_nm, radius_nm):
    """Truth by brute force: the disc as the mean of point emitters on a polar grid (Gauss nodes
    in r², uniform in angle), each imaged on its own."""
    scope = Microscope(na=na, n_medium=n_medium, wavelength_nm=600.0, pixel_size_nm=pixel_nm)
    wave = scope.wavefront_nm({"astig_vertical": 40.0, "coma_x": 30.0})
    defocus = np.array([0.0, 500.0])
    u, w_u = np.polynomial.legendre.leggauss(6)
    r = radius_nm * np.sqrt((u + 1) / 2) / pixel_nm  # px
    angle = 2 * np.pi * (np.arange(12) + 0.5) / 12
    points = [scope.pixel_image(0.2 + ri * np.cos(a), -0.1 + ri * np.sin(a), wave, defocus, 15)
              for ri in r for a in angle]  # fmt: skip
    brute = np.tensordot(np.repeat(w_u / 2 / 12, 12), np.array(points), axes=(0, 0))
    disc = scope.pixel_image(0.2, -0.1, wave, defocus, 15,
                             disc_radius_nm=np.full(2, radius_nm))  # fmt: skip
    point = scope.pixel_image(0.2, -0.1, wave, defocus, 15)
    assert np.abs(point - brute).max() > 0.02 * brute.max()  # the disc's extent shows
    np.testing.assert_allclose(disc, brute, atol=1e-4 * brute.max())


def test_fields_are_not_low_order_polynomials():
    fields = AberrationFields.random((128, 128), seed=3)
    yy, xx = np.mgrid[0:128, 0:128] / 127.0
    design = np.stack([xx**i * yy**j for i in range(4) for j in range(4 - i)], axis=-1)
    design = design.reshape(-1, design.shape[-1])
    for m in fields.maps:
        values = m.ravel()
        resid = values - design @ np.linalg.lstsq(design, values, rcond=None)[0]
        assert resid.std() > 0.15 * values.std()  # a cubic leaves a good part unexplained


@pytest.mark.parametrize("defocus_nm", [0.0, 400.0, 1500.0])
def test_a_rendered_patch_is_the_image_not_its_central_disc(defocus_nm):
    """Each plane of a patch holds the emitter's whole image within the patch: the centre of a
    whole pixel image, rings and comatic flare included, at any defocus and sub-pixel place. A
    patch cut to the spot's central disc near focus lost 13 % of this spot's light within 19 px
    at focus, and an astigmatic, comatic spot's fitted centre moved by −10 to +18 nm with its
    sub-pixel place."""
    from latentz.validation.datasets import render_patches

    fields = AberrationFields.random((64, 64), seed=3, pixel_size_nm=MICROSCOPE.pixel_size_nm)
    z = np.array([defocus_nm])
    for x, y in ((32.3, 31.8), (20.5, 40.1)):
        wave = MICROSCOPE.wavefront_nm(fields.coefficients([x], [y])[0])
        whole = MICROSCOPE.pixel_image(x - np.rint(x), y - np.rint(y), wave, z, 19)[0]
        patch = render_patches(MICROSCOPE, fields, x, y, z, 19)[0]
        np.testing.assert_allclose(patch, whole, rtol=0, atol=1e-6 * whole.max())


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


@pytest.mark.parametrize(("na", "n_medium"), [(0.4, 1.0), (1.2, 1.333), (1.49, 1.518)])
def test_in_focus_scalar_image_is_the_airy_disk_at_any_na(na, n_medium):
    # in focus the defocus phase vanishes and the plain scalar pupil is a uniform disk of radius
    # NA/λ, whose transform is the Airy pattern 2 J1(v)/v, v = 2π NA r / λ, at any NA
    scope = Microscope(na=na, n_medium=n_medium, wavelength_nm=560.0, radial_nodes=30,
                       azimuth_nodes=60)  # fmt: skip
    r = np.linspace(1.0, 1200.0, 60)
    intensity = scope.intensity(r, np.zeros(1), scope.wavefront_nm({}), np.zeros(1))[0, 0]
    v = 2 * np.pi * na * r / scope.wavelength_nm
    np.testing.assert_allclose(intensity / scope.pupil_area, (2 * j1(v) / v) ** 2, atol=1e-5)


def _axial_reference(scope: Microscope, z_nm: np.ndarray) -> np.ndarray:
    """On-axis intensity of the apodised scalar pupil by adaptive 1D quadrature (scipy.quad) of
    ∫ cos(θ)^(-1/2) exp(i k z sqrt(n² − NA² ρ²)) 2π ρ dρ (NA/λ)², normalised as the image is."""
    from scipy.integrate import quad

    cutoff, k, n = scope.na / scope.wavelength_nm, 2 * np.pi / scope.wavelength_nm, scope.n_medium

    def part(z, fn):
        def f(rho):
            axial = np.sqrt(n**2 - (scope.na * rho) ** 2)
            return fn((axial / n) ** -0.5 * np.exp(1j * k * z * axial)) * 2 * np.pi * rho

        return quad(f, 0.0, 1.0, limit=400)[0] * cutoff**2

    power = quad(lambda rho: (n / np.sqrt(n**2 - (scope.na * rho) ** 2)) * 2 * np.pi * rho,
                 0.0, 1.0)[0] * cutoff**2  # fmt: skip
    return np.array([part(z, np.real) ** 2 + part(z, np.imag) ** 2 for z in z_nm]) / power


def test_high_na_defocus_on_axis_matches_a_one_dimensional_integral():
    scope = Microscope(na=1.45, n_medium=1.518, wavelength_nm=600.0, apodize=True,
                       radial_nodes=60, azimuth_nodes=8)  # fmt: skip
    z = np.array([-900.0, -400.0, 0.0, 250.0, 700.0])
    got = scope.intensity(np.zeros(1), np.zeros(1), scope.wavefront_nm({}), z)[:, 0, 0]
    np.testing.assert_allclose(got, _axial_reference(scope, z), rtol=1e-4)


def test_vectorial_image_reduces_to_the_scalar_one_at_low_na():
    # at NA 0.2 cos θ > 0.98: the x and y dipoles' fields are the scalar field to O(θ²)
    low = {"na": 0.2, "wavelength_nm": 600.0, "pixel_size_nm": 200.0}
    scalar = Microscope(**low).pixel_image(0.0, 0.0, np.zeros(800), [0.0, 1500.0], 15)
    vector = Microscope(**low, vectorial=True).pixel_image(0.0, 0.0, np.zeros(800),
                                                           [0.0, 1500.0], 15)  # fmt: skip
    np.testing.assert_allclose(vector, scalar, atol=0.02 * scalar.max())


def test_vectorial_image_at_high_na_is_round_wider_and_holds_every_photon():
    scope = Microscope(na=1.4, n_medium=1.518, wavelength_nm=600.0, pixel_size_nm=40.0,
                       apodize=True, vectorial=True, radial_nodes=30, azimuth_nodes=60)  # fmt: skip
    flat = np.zeros(30 * 60)
    image = scope.pixel_image(0.0, 0.0, flat, [0.0], 61)[0]
    # an isotropic emitter has no preferred direction in the plane: the image is symmetric
    np.testing.assert_allclose(image, image.T, atol=1e-6 * image.max())
    np.testing.assert_allclose(image, image[::-1], atol=1e-6 * image.max())
    # the axial dipole's ring and the apodisation widen the spot beyond the scalar Airy disk
    airy = Microscope(na=1.4, n_medium=1.518, wavelength_nm=600.0, pixel_size_nm=40.0,
                      radial_nodes=30, azimuth_nodes=60).pixel_image(0.0, 0.0, flat, [0.0], 61)[0]
    r2 = (np.arange(61)[:, None] - 30) ** 2 + (np.arange(61)[None, :] - 30) ** 2

    def second_moment(img):
        inner = r2 <= 6**2
        return np.sum(img[inner] * r2[inner]) / np.sum(img[inner])
    assert second_moment(image) > 1.05 * second_moment(airy)
    # normalised to one photon over the plane (Parseval): the 2.4 µm patch holds less than all
    # of it, and more than 1 - 2 x the scalar Airy tail beyond its inscribed disk, 2 / (π v)
    v = 2 * np.pi * 1.4 / 600.0 * 30.5 * 40.0
    assert 1 - 2 * 2 / (np.pi * v) < image.sum() < 1.0
    assert airy.sum() < image.sum() + 2 / (np.pi * v)


def test_axial_dipole_alone_images_as_a_ring():
    scope = Microscope(na=1.4, n_medium=1.518, wavelength_nm=600.0, vectorial=True,
                       radial_nodes=30, azimuth_nodes=60)  # fmt: skip
    z_dipole = scope._factors[[2, 5]]  # E_x, E_y of the dipole along the optical axis
    r = np.array([0.0, 150.0])
    on = sum(np.abs(scope.amplitude(r, np.zeros(1), np.zeros(30 * 60), [0.0], factor=f))[0, 0]
             ** 2 for f in z_dipole)  # fmt: skip
    assert on[0] < 1e-6 * on[1]  # dark on the axis, bright off it

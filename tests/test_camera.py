import numpy as np
import pytest
from pixel_gaussian import pixel_profile

from latentz.camera import Camera


def test_to_photons_applies_offset_gain_and_flatfield():
    flat = np.full((4, 5), 2.0)
    cam = Camera(offset=100.0, gain=0.5, flatfield=flat)
    adu = np.full((3, 2, 2), 140.0)
    photons = cam.to_photons(adu, origin=(1, 2))
    # (140 - 100) * 0.5 / 2 = 10 photoelectrons in every pixel
    np.testing.assert_allclose(photons, 10.0)


def test_to_adu_inverts_to_photons_without_flatfield():
    cam = Camera(offset=400.0, gain=0.1)
    rng = np.random.default_rng(0)
    photons = rng.uniform(0, 1e4, size=(2, 6, 6))
    np.testing.assert_allclose(cam.to_photons(cam.to_adu(photons)), photons, rtol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gain": 0.0}, "gain"),
        ({"gain": -1.0}, "gain"),
        ({"pixel_size_nm": 0.0}, "pixel_size_nm"),
        ({"pixel_size_nm": float("nan")}, "pixel_size_nm"),
        ({"readnoise": -0.1}, "readnoise"),
        ({"offset": float("inf")}, "offset"),
        ({"flatfield": np.zeros((3, 3))}, "flatfield"),
        ({"flatfield": np.ones(3)}, "flatfield"),
    ],
)
def test_bad_parameters_raise_naming_the_parameter(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Camera(**kwargs)


def test_non_numeric_gain_is_a_type_error():
    with pytest.raises(TypeError, match="gain"):
        Camera(gain="fast")


def test_roi_outside_flatfield_is_refused():
    cam = Camera(flatfield=np.ones((4, 4)))
    with pytest.raises(ValueError, match="flatfield"):
        cam.to_photons(np.ones((3, 3)), origin=(2, 2))


def test_camera_is_immutable():
    cam = Camera()
    with pytest.raises(AttributeError):
        cam.gain = 2.0


def _gaussian_spots(
    n: int, size: int, photons: float, background: float, sigma_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Expected photoelectrons (n, size, size) of round Gaussian spots integrated over each
    pixel, and their true centres (n, 2) as (x, y) px, uniform within ±0.5 px of the middle."""
    centres = (size - 1) / 2 + rng.uniform(-0.5, 0.5, (n, 2))
    sigma = np.full(n, sigma_px)
    spots = (photons * pixel_profile(centres[:, 1], sigma, size)[:, :, None]
             * pixel_profile(centres[:, 0], sigma, size)[:, None, :])  # fmt: skip
    return spots + background, centres


def test_emccd_camera_gives_errors_that_cover():
    """EMCCD frames (gamma-distributed gain register, `simulate.emccd`) of spots at known
    places: with `Camera.emccd`, the fitted 1σ covers 68 % of the position errors; with the
    same datasheet values in a plain Camera, which takes the counts as Poisson, it covers
    about half (σ √2 too small), and photons are the photoelectrons, not half."""
    from latentz.fit import fit_rois
    from latentz.simulate.emccd import expose_emccd

    rng = np.random.default_rng(7)
    n, photons = 1500, 2000.0
    expected, centres = _gaussian_spots(n, 11, photons, 10.0, 1.3, rng)
    adu = expose_emccd(expected, rng, em_gain=100.0, e_per_adu=10.0, readnoise_e=50.0,
                       offset_adu=100.0)  # fmt: skip
    datasheet = dict(offset=100.0, gain=10.0 / 100.0, readnoise=50.0 / 100.0)
    for camera, band, share in (
        (Camera.emccd(**datasheet), (0.635, 0.73), 0.5),
        (Camera(**datasheet), (0.0, 0.6), 1.0),
    ):
        fit = fit_rois(adu, camera=camera)
        ok = fit["converged"].to_numpy()
        assert ok.mean() > 0.99
        for axis, column in ((0, "x"), (1, "y")):
            error = np.abs(fit[column].to_numpy() - centres[:, axis])[ok]
            covered = float(np.mean(error <= fit[f"{column}_err"].to_numpy()[ok]))
            assert band[0] <= covered <= band[1], (camera, column, covered)
        median = float(np.median(fit["photons"].to_numpy()[ok]))
        assert abs(median / photons - share) < 0.03 * share, (camera, median)

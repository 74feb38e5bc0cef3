import numpy as np
import pytest

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

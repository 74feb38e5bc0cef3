"""Rendering recovers a structure of known geometry: rings of known diameter, at known z."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
from structures import rings

import latentz as lz
from latentz.analysis import density_images, write_render

PIXEL_NM = 5.0


def _ring_diameters(brightness: np.ndarray, centres: np.ndarray, diameter: float) -> np.ndarray:
    """Twice the brightness-weighted mean distance from each true centre, within 0.8 diameters
    (the rings are 3 diameters apart)."""
    rows, cols = np.indices(brightness.shape)
    found = []
    for cx, cy in centres:
        r = np.hypot((cols + 0.5) * PIXEL_NM - cx, (rows + 0.5) * PIXEL_NM - cy)
        near = r < 0.8 * diameter
        found.append(2 * np.sum(brightness[near] * r[near]) / np.sum(brightness[near]))
    return np.array(found)


@pytest.mark.parametrize("seed", range(4))
def test_rendered_rings_have_their_true_diameter(seed):
    """Random rings (diameter 150-300 nm, precision 4-10 nm): the rendered ring's diameter is
    within 5 % of truth. A ring blurred by a Gaussian of sigma (precision and the render's own
    blur, sqrt(2) x precision) has its mean radius out by sigma^2 / 2R: at most 1.8 % here; 5 %
    is the requirement."""
    rng = np.random.default_rng(seed)
    diameter = rng.uniform(150, 300)
    precision = rng.uniform(4, 10)
    field = 4000.0
    locs, centres = rings(
        rng, n_rings=8, diameter_nm=diameter, precision_nm=precision, per_ring=400, field_nm=field
    )
    rgb = lz.render(locs, pixel_nm=PIXEL_NM, extent=(0, field, 0, field))
    side = int(np.ceil(field / PIXEL_NM)) + 1
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    assert rgb.shape[0] > side and rgb.shape[1] > side  # the side view and colour bar beside it
    xy_view = rgb[:side, :side].max(axis=2).astype(float)  # top left, pixel for pixel
    found = _ring_diameters(xy_view, centres, diameter)
    np.testing.assert_array_less(np.abs(found / diameter - 1), 0.05)


def test_colour_is_each_rings_true_z():
    """The density-weighted z of each ring's pixels is its true z, within 5 sigma of the mean of
    its localizations' z errors (400 per ring, sigma_z 25 nm: 5 x 1.25 nm)."""
    rng = np.random.default_rng(7)
    locs, centres = rings(
        rng, n_rings=6, diameter_nm=200, precision_nm=10, per_ring=400, field_nm=3000
    )
    views = density_images(locs, pixel_nm=PIXEL_NM, extent=(0, 3000, 0, 3000))
    grid, dens, mean_z = views["xy"]
    rows, cols = np.indices(dens.shape)
    for k, (cx, cy) in enumerate(centres):
        near = np.hypot((cols + 0.5) * PIXEL_NM - cx, (rows + 0.5) * PIXEL_NM - cy) < 160
        z = np.sum(dens[near] * np.nan_to_num(mean_z[near])) / np.sum(dens[near])
        assert abs(z - locs["z_true"].iloc[k * 400]) < 5 * 25 / np.sqrt(400)


def test_tiff_carries_the_pixel_size(tmp_path):
    rng = np.random.default_rng(3)
    locs, _ = rings(rng, n_rings=3, diameter_nm=200, precision_nm=8, per_ring=200, field_nm=2000)
    path = write_render(locs, tmp_path / "image.tif", pixel_nm=7.5)
    with tifffile.TiffFile(path) as tif:
        image = tif.asarray()
        x_resolution = tif.pages[0].tags["XResolution"].value
        unit = tif.imagej_metadata["unit"]
    assert image.dtype == np.float32 and image.shape[0] == 2
    assert x_resolution[1] / x_resolution[0] == pytest.approx(7.5)
    assert unit == "nm"
    # the density channel counts every localization once (the blur keeps the sum)
    assert image[0].sum() == pytest.approx(len(locs), rel=0.01)


def test_bad_blur_says_what_to_give():
    rng = np.random.default_rng(0)
    locs, _ = rings(rng, n_rings=2, diameter_nm=200, precision_nm=8, per_ring=50, field_nm=2000)
    with pytest.raises(ValueError, match="blur"):
        lz.render(locs, blur="sharp")
    with pytest.raises(ValueError, match="larger pixel_nm"):
        lz.render(locs, pixel_nm=0.1)

"""Where the CLI's camera comes from: file metadata (OME-TIFF, ImageJ) and estimates from the
images, against values written into the files or used to make the images."""

import numpy as np
import pytest
import tifffile
from scipy import stats

from latentz.camera.source import (
    camera_for_stacks,
    estimate_gain,
    estimate_offset,
    pixel_size_from_metadata,
)


def test_pixel_size_from_ome_and_imagej_metadata(tmp_path):
    image = np.zeros((3, 16, 16), np.uint16)
    ome = tmp_path / "a.ome.tif"
    tifffile.imwrite(ome, image, metadata={"axes": "ZYX", "PhysicalSizeX": 0.108})
    assert pixel_size_from_metadata(ome) == pytest.approx((108.0, "OME-TIFF PhysicalSizeX"))
    imagej = tmp_path / "b.tif"
    tifffile.imwrite(
        imagej, image, imagej=True, resolution=(1 / 0.16, 1 / 0.16), metadata={"unit": "um"}
    )
    size, where = pixel_size_from_metadata(imagej)
    assert size == pytest.approx(160.0, rel=1e-4) and where == "ImageJ resolution"
    plain = tmp_path / "c.tif"
    tifffile.imwrite(plain, image, photometric="minisblack")
    assert pixel_size_from_metadata(plain) is None


def _darkest_electrons_quantiles(photons, read_sigma, q):
    """Quantiles ``q`` of the smallest of independent Poisson(photons) + N(0, read_sigma)
    electron counts: P(min > t) is the product of each pixel's 1 − F(t), where
    F(t) = Σ_k Poisson(k) Φ((t − k) / read_sigma)."""
    lam = photons.ravel()[photons.ravel() < 60]  # brighter pixels are never the darkest
    k = np.arange(120)[:, None]
    t = np.linspace(-25.0, 10.0, 701)  # 0.05 e- steps
    log_above = np.zeros_like(t)
    for chunk in np.array_split(lam, max(1, lam.size // 2000)):
        weights = stats.poisson.pmf(k, chunk[None, :])  # (k, pixel)
        below = stats.norm.cdf((t[:, None] - k.T) / read_sigma) @ weights  # (t, pixel)
        log_above += np.log1p(-np.clip(below, 0.0, 1.0 - 1e-16)).sum(axis=1)
    return np.interp(q, 1.0 - np.exp(log_above), t)


@pytest.mark.parametrize("gain", [0.1, 0.5, 2.0])
def test_gain_and_offset_estimates_from_a_through_focus_stack(gain):
    # a spot that widens slowly through 40 planes on a 10-photon background; Poisson light,
    # 2 e- read noise, converted to ADU with `gain` e-/ADU and a 100 ADU offset
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:48, :48]
    width = np.linspace(1.5, 3.0, 40)[:, None, None]
    photons = 10 + 4000 / (2 * np.pi * width**2) * np.exp(
        -((xx - 24) ** 2 + (yy - 24) ** 2) / (2 * width**2)
    )
    electrons = rng.poisson(photons) + rng.normal(0, 2.0, photons.shape)
    adu = np.round(electrons / gain + 100)
    # the variance of a pixel grows as its mean / gain; planes differ little (slow widening)
    assert estimate_gain([adu]) == pytest.approx(gain, rel=0.1)
    # the offset estimate is the darkest pixel of every other plane (40 // 16 = 2): it lies
    # where the darkest of those ~46,000 Poisson + read-noise counts falls, which this model
    # puts, with 99.9 % probability, between these electron counts (±0.5 ADU of rounding)
    low, high = _darkest_electrons_quantiles(photons[::2], 2.0, [0.0005, 0.9995])
    offset = estimate_offset([adu])
    low, high = 100 + low / gain - 0.5, 100 + high / gain + 0.5
    print(f"gain {gain}: offset {offset:.1f} ADU in {low:.1f}..{high:.1f}")
    assert low <= offset <= high


def test_the_camera_line_names_every_source(tmp_path):
    rng = np.random.default_rng(2)
    stack = 100 + rng.poisson(20, (10, 32, 32)).astype(float)
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, stack.astype(np.uint16))
    camera, line = camera_for_stacks([stack], path, {"gain": 0.5, "offset": None})
    assert camera.gain == 0.5 and camera.offset == stack.min()
    assert "gain 0.5 e-/ADU (given)" in line and "(estimated: image minimum)" in line
    assert "give --pixel-size-nm" in line

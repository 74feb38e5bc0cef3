"""The fit's part of z_err_nm against the scatter of the calibration's own images
(:attr:`Calibration.noise_scale`): images rendered here (a pixel-integrated astigmatic Gaussian,
Poisson light, a known gain), not by latentz; truth is the gain they were made with."""

import numpy as np
import pytest
from scipy.special import erf

import latentz as lz
from latentz.calibration.errors import measured_noise, noise_by_z

GAIN = 1.0  # e-/ADU the images are made with
Z_NM = np.arange(-800.0, 800.1, 20.0)


def _render(z_nm: np.ndarray, spots, size: int, seed: int, averaged=None) -> np.ndarray:
    """(n_z, size, size) ADU: 20,000-photon spots at ``spots`` ((x, y) px), widths 1.5 px at
    focus, foci ±300 nm apart along the camera axes (a cylindrical lens), 20 photons of
    background, offset 100 ADU; each plane the mean of ``averaged(z)`` frames (1 by default)."""
    rng = np.random.default_rng(seed)
    edges = np.arange(size + 1) - 0.5
    wx = 1.5 * np.sqrt(1 + ((z_nm - 300) / 600) ** 2)
    wy = 1.5 * np.sqrt(1 + ((z_nm + 300) / 600) ** 2)

    def share(centre, w):  # fraction of the spot in each pixel along one axis
        return np.diff(erf((edges[None, :] - centre) / (np.sqrt(2) * w[:, None])), axis=1) / 2

    mean = np.full((z_nm.size, size, size), 20.0)
    for x, y in spots:
        mean += 20000.0 * share(y, wy)[:, :, None] * share(x, wx)[:, None, :]
    frames = np.ones(z_nm.size, int) if averaged is None else averaged(z_nm)
    light = [rng.poisson(np.repeat(m[None], n, axis=0)).mean(axis=0)
             for m, n in zip(mean, frames, strict=True)]  # fmt: skip
    return np.stack(light) / GAIN + 100.0


def _stack(seed: int) -> np.ndarray:
    """(n_z, 21, 21) ADU: one spot in the middle (:func:`_render`)."""
    return _render(Z_NM, [(10.0, 10.0)], 21, seed)


def _odd_even(gain: float, seeds=range(4)) -> tuple[float, np.ndarray, np.ndarray]:
    camera = lz.Camera(offset=100.0, gain=gain, readnoise=0.0, pixel_size_nm=100.0)
    cal = lz.calibrate(_stack(0)[1::2], Z_NM[1::2], camera=camera, roi_size=13)
    errors, sigmas = [], []
    for seed in seeds:  # new noise on the even planes
        locs = lz.localize(_stack(100 + seed)[0::2], calibration=cal)
        true_z = Z_NM[0::2][locs["frame"].to_numpy()] - cal.particles["z_f"].iloc[0]
        near = (np.abs(true_z) <= 500) & locs["in_range"].to_numpy()
        errors.append(locs["z_nm"].to_numpy()[near] - true_z[near])
        sigmas.append(locs["z_err_nm"].to_numpy()[near])
    return cal.noise_scale, np.concatenate(errors), np.concatenate(sigmas)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_gain_that_overstates_the_noise_is_measured_and_the_errors_still_cover():
    right, err_r, sig_r = _odd_even(GAIN)
    # told 4x fewer electrons per ADU: the noise model's variance is 4x the images', σ 2x
    low, err_l, sig_l = _odd_even(GAIN / 4)
    assert right == 1.0
    # 0.5, within twice the sampling error of the RMS of ~40 calibration images (1/√80 = 11 %)
    assert 0.39 <= low <= 0.61, low
    # 72 % and 67 % (100 spots each); without the scale the low gain's errors cover 91 %
    n = err_l.size
    tolerance = 2.58 * np.sqrt(0.6827 * 0.3173 / n)
    for err, sig in ((err_r, sig_r), (err_l, sig_l)):
        assert abs(np.mean(np.abs(err) <= sig) - 0.6827) <= tolerance


def _averaged(z_nm: np.ndarray) -> np.ndarray:
    """Frames averaged into each plane: 1 at focus, 9 at ±800 nm; the images' noise is
    1/sqrt of that of one frame, which the camera model says."""
    return np.round(1 + 8 * (np.asarray(z_nm) / 800.0) ** 2).astype(int)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_noise_scale_that_varies_with_z_is_followed_and_the_errors_cover_at_every_z():
    """Four beads calibrate; five emitters elsewhere in the field, at other depths, are
    localized. Each plane of both is the mean of a number of frames that grows away from focus,
    so the images' noise falls from 1 to 1/3 of what the camera model says: one factor for all
    z (0.74 here) over-covers far from focus (84 %) and under-covers near it."""
    z_cal, z_test = np.arange(-800.0, 800.1, 10.0), np.arange(-795.0, 795.1, 10.0)
    beads = ((16.3, 15.8), (15.6, 48.2), (48.4, 16.1), (47.7, 47.5))
    emitters = ((32.3, 31.7), (31.6, 16.4), (16.2, 32.5), (47.6, 31.8), (32.4, 47.7))
    camera = lz.Camera(offset=100.0, gain=GAIN, readnoise=0.0, pixel_size_nm=100.0)
    cal = lz.calibrate(_render(z_cal, beads, 64, 0, _averaged), z_cal, camera=camera,
                       roi_size=13)  # fmt: skip
    grid, scale = cal.noise_scale_by_z
    for lo, hi in ((-700, -500), (-150, 150), (500, 700)):
        planes = (z_cal >= lo) & (z_cal <= hi)
        truth = np.sqrt(np.mean(1 / _averaged(z_cal[planes])))
        found = np.median(scale[(grid >= lo) & (grid <= hi)])
        # the scale over m images is known to 1/sqrt(2 m): 3x that, m = 4 beads' planes there
        assert abs(found / truth - 1) <= 3 / np.sqrt(2 * 4 * planes.sum()), (lo, found, truth)
    errors, sigmas, depths = [], [], []
    for seed in (1, 2):
        locs = lz.localize(_render(z_test, emitters, 64, seed, _averaged), calibration=cal)
        locs = locs[locs["in_range"].to_numpy()]
        depths.append(z_test[locs["frame"].to_numpy()])
        errors.append(locs["z_nm"].to_numpy() - depths[-1])
        sigmas.append(locs["z_err_nm"].to_numpy())
    depth, error, sigma = (np.concatenate(v) for v in (depths, errors, sigmas))
    error -= np.median(error[np.abs(depth) <= 600])  # one offset: the calibration's z origin
    for part in (np.abs(depth) < 300, (np.abs(depth) >= 300) & (np.abs(depth) <= 600)):
        # 600 spots each: the binomial band at 2.58 sigma is ±4.9 %; the field model's
        # cross-validated part adds a little (measured 70-76 % in four quarters)
        assert 0.60 <= np.mean(np.abs(error[part]) <= sigma[part]) <= 0.76, part.sum()


def test_measured_noise_scales_only_a_significant_deficit():
    rng = np.random.default_rng(0)
    predicted = np.full((2, 200), 2.0)
    residual = rng.normal(0.0, 1.0, (2, 200))  # half the predicted scatter
    assert measured_noise(residual, predicted, n_params=5) == pytest.approx(0.5, abs=0.05)
    assert measured_noise(2 * residual, predicted, n_params=5) == 1.0  # as predicted
    assert measured_noise(6 * residual, predicted, n_params=5) == 1.0  # more: never scaled up
    assert measured_noise(residual, np.full((2, 200), np.nan), n_params=5) == 1.0


def test_measured_noise_is_not_ruled_by_flat_planes():
    """Where a curve is flat its predicted error is huge, while the curve, fitted to those very
    images, leaves them small residuals; they count once, like every other image. A ratio of RMS
    values would give ~0.05 here."""
    rng = np.random.default_rng(1)
    predicted = rng.lognormal(np.log(5.0), 0.3, (40, 100))
    residual = rng.normal(0.0, predicted)
    predicted[:, :2] = 3000.0  # the flat ends of each curve
    assert measured_noise(residual, predicted, n_params=5) >= 0.95
    assert measured_noise(residual / 2, predicted, n_params=5) == pytest.approx(0.5, abs=0.03)


def test_measured_noise_counts_the_images_each_curve_was_fitted_to():
    """An order-16 curve fitted to 90 images of scatter 1, of which only the middle 44 count
    (the usable planes), each predicted at 2: the scale is 0.5. Correcting the residuals for 17
    parameters among the 44 images that count, instead of the 90 the curve was fitted to,
    gives 0.60 here."""
    rng = np.random.default_rng(2)
    z = np.linspace(-1.0, 1.0, 90)
    noise = rng.normal(0.0, 1.0, (40, z.size))
    residual = np.array([y - np.polynomial.Polynomial.fit(z, y, 16)(z) for y in noise])
    predicted = np.where(np.abs(z) <= 0.48, 2.0, np.nan) * np.ones((40, 1))
    fitted = np.full(40, z.size)
    scale = measured_noise(residual, predicted, n_params=17, n_fitted=fitted)
    # sampling error of an RMS over 40 x 44 images: 0.5 / sqrt(2 x 1760) = 0.008, 3x that
    assert scale == pytest.approx(0.5, abs=0.025), scale


def test_noise_by_z_follows_the_scatter_in_windows_of_enough_images():
    """Squared normalised residuals of a scale that falls from 1 at focus to 0.3 at ±600 nm:
    the curve follows it within its windows' sampling error, never above 1; too few images
    give no curve (the one factor serves)."""
    rng = np.random.default_rng(4)
    z = rng.uniform(-600.0, 600.0, 2000)
    truth = 1.0 - 0.7 * (z / 600.0) ** 2
    free = np.ones(z.size)
    grid, scale = noise_by_z(z, (truth * rng.normal(0.0, 1.0, z.size)) ** 2, free)
    assert np.all(np.diff(grid) > 0) and scale.max() <= 1.0
    inside = np.abs(grid) <= 550  # a window of 125 images spans about 75 nm
    expected = 1.0 - 0.7 * (grid[inside] / 600.0) ** 2
    # each window's scale is known to 1/sqrt(2 × 125) = 6 %: 4x that, over 1,900 windows
    np.testing.assert_allclose(scale[inside], expected, rtol=0.25)
    assert noise_by_z(z[:23], np.ones(23), free[:23])[0].size == 0  # under two windows of 12
    # residuals that keep a third of their images' noise (an inverse of 16 parameters through
    # 24 images) hold 8 degrees of freedom: not one window's worth, so no curve
    assert noise_by_z(z[:24], np.ones(24), np.full(24, 1 / 3))[0].size == 0
    # the same residuals weighted by what they keep: r² = scatter² / (1 − h) on average
    grid, scale = noise_by_z(z, (truth * rng.normal(0.0, 1.0, z.size)) ** 2 * 0.5, free * 0.5)
    np.testing.assert_allclose(
        scale[np.abs(grid) <= 550], 1.0 - 0.7 * (grid[np.abs(grid) <= 550] / 600.0) ** 2, rtol=0.3
    )


def test_a_curve_through_barely_more_images_than_parameters_says_nothing():
    """18 images through a 17-parameter curve leave one residual degree of freedom, whose
    square is often far below its mean: residuals at 0.3 of what the noise leaves are no
    evidence that the images scatter less than their fit errors, so r stays 1 (such a one-bead
    calibration had r = 0.37, and its z errors were reported 3x too small)."""
    predicted = np.full((1, 18), 5.0)
    left = 5.0 * np.sqrt(1 / 18)  # the RMS residual that noise of 5 nm leaves, on average
    residual = np.full((1, 18), 0.3 * left)
    assert measured_noise(residual, predicted, n_params=17, n_fitted=np.array([18])) == 1.0
    # the same residuals with many images per parameter are evidence: r = 0.3
    many = np.full((40, 180), 0.3 * 5.0 * np.sqrt(163 / 180))
    scale = measured_noise(many, np.full((40, 180), 5.0), n_params=17)
    assert scale == pytest.approx(0.3, rel=1e-9)

"""The fit's part of z_err_nm against the scatter of the calibration's own images
(:attr:`Calibration.noise_scale`): images rendered here (a pixel-integrated astigmatic Gaussian,
Poisson light, a known gain), not by latentz; truth is the gain they were made with."""

import numpy as np
import pytest
from scipy.special import erf

import latentz as lz
from latentz.calibration.errors import measured_noise

GAIN = 1.0  # e-/ADU the images are made with
Z_NM = np.arange(-800.0, 800.1, 20.0)


def _stack(seed: int) -> np.ndarray:
    """(n_z, 21, 21) ADU: 20,000 photons, widths 1.5 px at focus, foci ±300 nm apart along the
    camera axes (a cylindrical lens), 20 photons of background, offset 100 ADU."""
    rng = np.random.default_rng(seed)
    edges = np.arange(22) - 10.5
    wx = 1.5 * np.sqrt(1 + ((Z_NM - 300) / 600) ** 2)
    wy = 1.5 * np.sqrt(1 + ((Z_NM + 300) / 600) ** 2)

    def share(w):  # fraction of the spot in each pixel along one axis
        return np.diff(erf(edges[None, :] / (np.sqrt(2) * w[:, None])), axis=1) / 2

    mean = 20.0 + 20000.0 * share(wy)[:, :, None] * share(wx)[:, None, :]
    return rng.poisson(mean) / GAIN + 100.0


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

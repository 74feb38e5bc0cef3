"""Test frames from a measured PSF (simulate.bead_psf) and the EMCCD readout (simulate.emccd)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.special import erf

from latentz.simulate.bead_psf import BeadPSF
from latentz.simulate.emccd import expose_emccd

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def _pixel_gaussian(x0, y0, sigma, shape):
    """Unit-sum image of a Gaussian integrated over each pixel (x = column)."""

    def axis(c, n):
        edges = (np.arange(n + 1) - 0.5 - c) / (np.sqrt(2) * sigma)
        return np.diff(erf(edges)) / 2

    return np.outer(axis(y0, shape[0]), axis(x0, shape[1]))


def _gaussian_stack(centres, sigmas, shape=(60, 90)):
    return np.array(
        [sum(_pixel_gaussian(x, y, s, shape) * 5e4 for x, y in centres) for s in sigmas]
    )


def test_rendered_emitter_is_the_shifted_bead_image():
    # Noise-free pixel-integrated Gaussians (sigma 1.5 and 2.5 px) at two sub-pixel places give
    # the PSF; an emitter rendered elsewhere must match the analytic image there. The Fourier
    # shift is exact up to the spectrum beyond Nyquist, exp(-2 pi^2 sigma^2 / 4) = 1.5e-5 of the
    # peak spectrum for sigma 1.5 px, so 1e-4 of the peak pixel is a safe bound.
    sigmas = (1.5, 2.5)
    psf = BeadPSF.from_stack(
        _gaussian_stack([(20.3, 30.6), (70.8, 29.1)], sigmas),
        [0.0, 100.0],
        [(20.3, 30.6), (70.8, 29.1)],
    )
    emitters = pd.DataFrame(
        {"frame": [0, 1], "x": [17.37, 30.5], "y": [22.81, 19.0], "z_nm": [0.0, 100.0],
         "photons": [1000.0, 500.0]}
    )  # fmt: skip
    frames = psf.render(emitters, n_frames=2, frame_shape=(48, 64), background=3.0)
    for k, row in emitters.iterrows():
        truth = 3.0 + row.photons * _pixel_gaussian(row.x, row.y, sigmas[k], (48, 64))
        peak = truth.max() - 3.0
        np.testing.assert_allclose(frames[k], truth, atol=1e-4 * peak)


def test_z_between_planes_blends_the_two_images_linearly():
    psf = BeadPSF.from_stack(_gaussian_stack([(40.0, 30.0)], (1.5, 2.5)), [0.0, 100.0], [(40, 30)])
    mid = psf.image([0.2], [-0.3], [25.0])[0]
    ends = psf.image([0.2, 0.2], [-0.3, -0.3], [0.0, 100.0])
    np.testing.assert_allclose(mid, 0.75 * ends[0] + 0.25 * ends[1], atol=1e-12)
    assert mid.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="within the measured 0…100 nm"):
        psf.image([0.0], [0.0], [120.0])


def test_bead_too_near_the_edge_is_refused():
    with pytest.raises(ValueError, match="lies within 15 px of the edge"):
        BeadPSF.from_stack(np.zeros((2, 40, 40)), [0.0, 1.0], [(10.0, 20.0)])


def test_emccd_mean_and_excess_noise():
    # 50 photoelectrons, EM gain 100, 10 e-/ADU, 50 e- read noise: mean 100 + 50*100/10 ADU and
    # variance (2 * 50 * 100^2 + 50^2) / 10^2 = 10025 ADU^2 (excess noise factor sqrt 2) + 1/12
    # for rounding. 40,000 pixels: standard errors 0.5 ADU for the mean and 0.7 % for the
    # variance (a gamma-Poisson compound is near normal at n = 50); the bounds are 4 of them.
    rng = np.random.default_rng(3)
    adu = expose_emccd(
        np.full((200, 200), 50.0), rng, em_gain=100, e_per_adu=10, readnoise_e=50, offset_adu=100
    ).astype(float)
    assert adu.mean() == pytest.approx(600.0, abs=2.0)
    assert adu.var() == pytest.approx(10025.0 + 1 / 12, rel=0.03)
    dark = expose_emccd(
        np.zeros((200, 200)), rng, em_gain=100, e_per_adu=10, readnoise_e=50, offset_adu=100
    ).astype(float)
    assert dark.mean() == pytest.approx(100.0, abs=4 * 5 / 200)
    assert dark.var() == pytest.approx(25.0 + 1 / 12, rel=0.03)


@pytest.mark.realdata
def test_psf_of_other_beads_reproduces_a_real_bead():
    # The SMLM 2016 AS stack: a PSF averaged from beads 3-5 and rendered at bead 0's true place
    # must fit bead 0's image better than the same PSF 100 nm off in z or 0.5 px off laterally
    # (a wrong shift sign, centring or z interpolation fails this).
    tifffile = pytest.importorskip("tifffile")
    path = DATA / "smlm2016-as-beads.tif"
    if not path.exists():
        pytest.skip(f"real data {path.name} not found in {DATA} (shared data folder absent)")
    stack = tifffile.imread(path).astype(float) - 100.0
    truth = pd.read_csv(DATA / "smlm2016-as-beads.csv")
    first = truth[truth.plane == 0].set_index("bead")
    centres = np.c_[first.x_nm / 100 - 0.5, first.y_nm / 100 - 0.5]  # corner to pixel centre
    z = np.sort(truth.z_nm.unique())
    psf = BeadPSF.from_stack(stack, z, centres[3:6])
    x, y = centres[0]
    col, row = round(x), round(y)
    for plane in (20, 60, 75, 100, 130):
        win = stack[plane, row - 15 : row + 16, col - 15 : col + 16]
        win = win - np.median(np.r_[win[0], win[-1], win[:, 0], win[:, -1]])

        def misfit(dx, dy, dz, win=win, plane=plane):
            em = pd.DataFrame({"frame": [0], "x": [15 + x - col + dx], "y": [15 + y - row + dy],
                               "z_nm": [z[plane] + dz], "photons": [win.sum()]})  # fmt: skip
            model = psf.render(em, n_frames=1, frame_shape=(31, 31), background=0.0)[0]
            return float(np.sum((win - model) ** 2 / (np.abs(model) + win.var() / 50)))

        best = misfit(0, 0, 0)
        for wrong in ((0.5, 0, 0), (0, 0.5, 0), (0, 0, 100), (0, 0, -100)):
            assert best < misfit(*wrong), (plane, wrong)

"""Tests of the simulated microscope against known physics and the camera model."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares

from latentz.camera import Camera
from latentz.simulate import AberrationMap, Optics, calibration_dataset, write_dataset
from latentz.simulate._kernels import mft_power, mft_power_reference
from latentz.simulate._render import expose


def _moments(img):
    y, x = np.mgrid[: img.shape[0], : img.shape[1]]
    s = img.sum()
    mx, my = (img * x).sum() / s, (img * y).sum() / s
    vx = (img * (x - mx) ** 2).sum() / s
    vy = (img * (y - my) ** 2).sum() / s
    cxy = (img * (x - mx) * (y - my)).sum() / s
    return vx, vy, cxy


def test_in_focus_psf_gaussian_sigma_and_normalisation():
    # Fine pixels (20 nm) so that pixelation does not widen the fitted Gaussian.
    optics = Optics(magnification=325.0)
    img = optics.psf(0.0, shape=(61, 61))[0]
    y, x = np.mgrid[:61, :61]

    def res(p):
        return p[0] * np.exp(-((x - p[1]) ** 2 + (y - p[2]) ** 2) / (2 * p[3] ** 2)) - img

    fit = least_squares(lambda p: res(p).ravel(), (img.max(), 30, 30, 10)).x
    sigma_nm = fit[3] * optics.pixel_size_nm
    assert abs(sigma_nm / (0.21 * 680 / 0.55) - 1) < 0.10
    # Sum over a 65 µm patch: the Airy wings beyond it hold < 0.5 % (1 - EE ~ 2/(π v)).
    wide = Optics(magnification=20.0, pupil_samples=128).psf(0.0, shape=(201, 201))[0]
    assert abs(wide.sum() - 1) < 0.01


def test_oblique_astigmatism_flips_ellipse_through_focus():
    optics = Optics()
    ab = AberrationMap.constant({5: 45.0})
    imgs = optics.psf([-1000.0, 1000.0], zernike_nm=ab.zernike_at(0, 0), shape=(40, 40))
    angles, rhos = [], []
    for img in imgs:
        vx, vy, cxy = _moments(img)
        angles.append(0.5 * math.degrees(math.atan2(2 * cxy, vx - vy)))
        rhos.append(cxy / math.sqrt(vx * vy))
    assert angles[0] == pytest.approx(45.0, abs=1.0)
    assert angles[1] == pytest.approx(-45.0, abs=1.0)
    assert rhos[0] > 0.05 and rhos[1] < -0.05


def test_field_curvature_moves_best_focus_by_the_coefficient():
    # d* = -c4 <Z4, n cos θ> / ||n cos θ - mean||² (paraxially 4√3 n c4 / NA²).
    optics = Optics()
    c4 = 20.0
    k = optics.focus_shift_per_defocus_nm()
    assert k == pytest.approx(4 * math.sqrt(3) / 0.55**2, rel=0.10)
    z = np.arange(-300.0, 1000.0, 20.0)
    peaks = []
    for coef in (0.0, c4):
        img = optics.psf(z, zernike_nm={4: coef}, shape=(21, 21))
        centre = img[:, 10, 10]
        i = int(np.argmax(centre))
        a, b, _ = np.polyfit(z[i - 2 : i + 3], centre[i - 2 : i + 3], 2)
        peaks.append(-b / (2 * a))
    assert peaks[1] - peaks[0] == pytest.approx(k * c4, rel=0.03)


def test_camera_mean_and_variance_match_model():
    cam = Camera(offset=100.0, gain=0.5, readnoise=1.5)
    n = 200 * 200
    for mu in (5.0, 300.0):
        adu = expose(np.full((1, 200, 200), mu), cam, np.random.default_rng(1)).astype(float)
        var = (mu + cam.readnoise**2) / cam.gain**2 + 1 / 12  # + rounding
        assert abs(adu.mean() - (cam.offset + mu / cam.gain)) < 4 * math.sqrt(var / n)
        assert abs(adu.var() - var) < 4 * var * math.sqrt(2 / (n - 1))
    sat = expose(np.full((1, 4, 4), 1e6), cam, np.random.default_rng(0))
    assert sat.dtype == np.uint16 and np.all(sat == 65535)


def test_kernel_matches_numpy_twin():
    rng = np.random.default_rng(0)
    field = (rng.normal(size=(3, 8, 8)) + 1j * rng.normal(size=(3, 8, 8))).astype(np.complex64)
    ay = (rng.normal(size=(5, 8)) + 1j * rng.normal(size=(5, 8))).astype(np.complex64)
    ax = (rng.normal(size=(8, 6)) + 1j * rng.normal(size=(8, 6))).astype(np.complex64)
    out = np.empty((3, 5, 6), np.float32)
    mft_power(field, ay, ax, out)
    np.testing.assert_allclose(out, mft_power_reference(field, ay, ax), rtol=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"na": 0.0}, "na"),
        ({"camera_pixel_um": -1.0}, "camera_pixel_um"),
        ({"na": 1.2}, "immersion_index"),
        ({"pupil_samples": 4}, "pupil_samples"),
    ],
)
def test_bad_optics(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Optics(**kwargs)


def test_bad_dataset_input():
    with pytest.raises(ValueError, match="n_particles"):
        calibration_dataset(n_particles=0)
    with pytest.raises(ValueError, match="Cannot place"):
        calibration_dataset(n_particles=50, n_stage_positions=1, frame_shape=(64, 64))
    with pytest.raises(ValueError, match="kind"):
        write_dataset("nonsense", "unused")


def test_calibration_truth_and_files(tmp_path):
    written = write_dataset("calibration", tmp_path, quick=True, seed=3)
    import tifffile

    truth = pd.read_csv(tmp_path / "calibration_truth.csv")
    meta = json.loads((tmp_path / "calibration_metadata.json").read_text())
    stacks = [tifffile.imread(p) for p in written if p.suffix == ".tif"]
    assert len(stacks) == len(meta["origins_row_col"]) and stacks[0].dtype == np.uint16
    assert stacks[0].shape[0] == len(meta["z_nm"])
    # The substrate is the stated plane: slope tan(2 mrad) per nm along the tilt direction.
    a = np.c_[truth.field_x, truth.field_y, np.ones(len(truth))]
    gx, gy, _ = np.linalg.lstsq(a, truth.z_surface_nm, rcond=None)[0]
    assert math.hypot(gx, gy) == pytest.approx(math.tan(2e-3) * 130.0, rel=1e-6)
    assert math.atan2(gy, gx) == pytest.approx(meta["tilt_direction_rad"], abs=1e-6)
    np.testing.assert_allclose(truth.z_focus_nm, truth.focus_defocus_nm - truth.z_nm)
    # The brightest plane of each good particle is near its true best focus.
    step = np.diff(meta["z_nm"])[0]
    for row in truth[~truth.defective].itertuples():
        stack = stacks[row.stack]
        r, c = round(row.y), round(row.x)
        peak = stack[:, r - 1 : r + 2, c - 1 : c + 2].astype(float).sum(axis=(1, 2))
        assert abs(meta["z_nm"][int(np.argmax(peak))] - row.z_focus_nm) <= 2.5 * step

"""Point emitters read through a calibration on 200 nm beads (``particle_diameter_nm``).

The optics are an astigmatic Gaussian PSF along the camera axes (principal widths
``s0 sqrt(1 + ((z ∓ c)/d)²)``, NA 1.4-like: 90 nm in focus, foci 800 nm apart), integrated over
each pixel. A bead is a uniform ball: its image is the mean of the point images of a cubic grid
of sources inside it, each at its own lateral and axial place. Test emitters are points at known
z; their truth is where they were put, on the axis whose z = 0 is the bead centres' focus (the
PSF is symmetric about it, so best focus is there for beads and points alike).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pixel_gaussian import pixel_profile

from latentz.calibration import Calibration, Traces, calibrate
from latentz.camera import Camera
from latentz.fit import fit_rois

PX_NM = 100.0
S0_NM, C_NM, D_NM = 90.0, 400.0, 500.0
ROI = 13
BEAD_NM = 200.0
CAMERA = Camera(offset=100.0, gain=1.0, readnoise=1.0, pixel_size_nm=PX_NM)
BEADS_PX = np.array([[15.3, 15.2], [44.6, 15.7], [15.8, 44.4], [44.2, 44.9]])
Z_NM = np.arange(-1000.0, 1000.1, 25.0)


def _sigmas_nm(z_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PSF widths along x and y (nm) at defocus ``z_nm``."""
    return (S0_NM * np.sqrt(1 + ((z_nm - C_NM) / D_NM) ** 2),
            S0_NM * np.sqrt(1 + ((z_nm + C_NM) / D_NM) ** 2))  # fmt: skip


def _points_image(x_px, y_px, z_nm, size: int) -> np.ndarray:
    """(m, size, size) pixel-integrated images of unit point sources."""
    sx, sy = _sigmas_nm(np.asarray(z_nm, float))
    return (pixel_profile(np.asarray(y_px, float), sy / PX_NM, size)[:, :, None]
            * pixel_profile(np.asarray(x_px, float), sx / PX_NM, size)[:, None, :])  # fmt: skip


def _ball(diameter_nm: float) -> np.ndarray:
    """(m, 3) sources (nm) on a cubic grid filling a ball of ``diameter_nm`` (one point if 0)."""
    if diameter_nm == 0:
        return np.zeros((1, 3))
    radius = diameter_nm / 2
    axis = np.linspace(-radius, radius, 11)
    grid = np.stack(np.meshgrid(axis, axis, axis), axis=-1).reshape(-1, 3)
    return grid[np.linalg.norm(grid, axis=1) <= radius]


def _stack(diameter_nm: float, seed: int = 0) -> np.ndarray:
    """(n_z, 60, 60) ADU through-focus stack of the four beads (2e5 photons, background 20)."""
    sources = _ball(diameter_nm)
    mean = np.full((Z_NM.size, 60, 60), 20.0)
    for x, y in BEADS_PX:
        col, row = int(x) - 12, int(y) - 12  # a 25 px window about the bead
        for z_index, z in enumerate(Z_NM):  # the piezo moves the sample: defocus z + dz
            images = _points_image(
                x - col + sources[:, 0] / PX_NM,
                y - row + sources[:, 1] / PX_NM,
                z + sources[:, 2],
                25,
            )
            mean[z_index, row : row + 25, col : col + 25] += 2e5 * images.mean(axis=0)
    rng = np.random.default_rng(seed)
    return rng.poisson(mean) + rng.normal(0, CAMERA.readnoise, mean.shape) + CAMERA.offset


def _calibration(diameter_nm: float, particle_diameter_nm: float | None) -> Calibration:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the nearest-particle field model of four beads
        return calibrate(_stack(diameter_nm), Z_NM, camera=CAMERA, shape="auto", roi_size=ROI,
                         field_model="nearest", tilt=False,
                         particle_diameter_nm=particle_diameter_nm)  # fmt: skip


@pytest.fixture(scope="module")
def emitters():
    """Fitted point emitters (5000 photons, background 10) at known z within ±500 nm, placed
    next to the beads, and their true z (nm)."""
    rng = np.random.default_rng(1)
    n = 240
    z_true = rng.uniform(-500, 500, n)
    offset = rng.uniform(-0.5, 0.5, (n, 2))
    centre = ROI // 2
    mean = 10.0 + 5000 * _points_image(centre + offset[:, 0], centre + offset[:, 1], z_true, ROI)
    rois = rng.poisson(mean) + rng.normal(0, CAMERA.readnoise, mean.shape)
    spots = fit_rois(rois, camera=Camera(offset=0.0, gain=1.0, readnoise=CAMERA.readnoise,
                                         pixel_size_nm=PX_NM))  # fmt: skip
    near = BEADS_PX[np.arange(n) % len(BEADS_PX)] + 3.0  # field place: near a bead
    spots = spots.assign(x=near[:, 0] + spots["x"] - centre, y=near[:, 1] + spots["y"] - centre)
    spots.attrs["roi_size"] = ROI
    return spots, z_true


def _z_errors(cal: Calibration, emitters) -> tuple[np.ndarray, np.ndarray]:
    """z error (nm) of the in-range emitters, and their true z."""
    spots, z_true = emitters
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        located = cal.apply(spots)
    ok = located["in_range"].to_numpy(bool) & spots["converged"].to_numpy(bool)
    return located["z_nm"].to_numpy(float)[ok] - z_true[ok], z_true[ok]


@pytest.fixture(scope="module")
def calibrations() -> dict[str, Calibration]:
    """Calibrations on the 200 nm beads as imaged ("beads") and given their diameter
    ("corrected"), and on point particles ("points")."""
    return {"beads": _calibration(BEAD_NM, None), "corrected": _calibration(BEAD_NM, BEAD_NM),
            "points": _calibration(0.0, None)}  # fmt: skip


@pytest.mark.slow
def test_bead_diameter_reads_point_emitters(calibrations, emitters):
    """Read through the 200 nm beads' own shapes, points are read farther from focus (they are
    more elliptical than the beads at the same z): a slope of z error against z. Taking the
    beads' d²/20 off the fits removes it, down to a calibration on point particles."""
    results = {}
    for label, cal in calibrations.items():
        err, z = _z_errors(cal, emitters)
        assert err.size > 0.9 * len(emitters[1])
        results[label] = (float(np.sqrt(np.mean(err**2))), float(np.polyfit(z, err, 1)[0]))
    (rms_beads, slope_beads), (rms_fixed, slope_fixed), (rms_points, slope_points) = (
        results["beads"], results["corrected"], results["points"])  # fmt: skip
    assert slope_beads > 0.04, results  # the bead calibration stretches point z by 6 %
    assert abs(slope_fixed) < 0.015, results
    assert abs(slope_points) < 0.015, results
    assert rms_fixed < 0.7 * rms_beads, results
    assert rms_fixed < 1.1 * rms_points, results


@pytest.mark.slow
def test_bead_diameter_is_recorded_and_saved(calibrations, tmp_path):
    """The option is recorded, and a saved calibration holds the point emitters' traces."""
    cal = calibrations["corrected"]
    assert cal.options["particle_diameter_nm"] == BEAD_NM
    assert calibrations["beads"].options["particle_diameter_nm"] is None
    path = tmp_path / "cal.h5"
    cal.save(path)
    again = Calibration.load(path)
    assert again.options["particle_diameter_nm"] == BEAD_NM
    for name in ("wx", "wy", "rho", "amplitude", "dim0_wx"):
        np.testing.assert_array_equal(again.traces[name], cal.traces[name])


def test_point_emitter_traces_undo_a_ball_blur():
    """A Gaussian image blurred by a ball of diameter d (covariance + d²/20 on the diagonal, the
    same photons) maps back to the point's widths, ρ and amplitude; errors scale to first
    order."""
    d_nm, px = 200.0, 100.0
    blur = d_nm**2 / 20 / px**2
    wx, wy, rho = np.array([[1.1, 2.0]]), np.array([[0.9, 1.3]]), np.array([[0.3, -0.6]])
    photons = 1e4
    amp = photons / (2 * np.pi * wx * wy * np.sqrt(1 - rho**2))
    bx, by = np.sqrt(wx**2 + blur), np.sqrt(wy**2 + blur)
    brho = rho * wx * wy / (bx * by)
    bamp = photons / (2 * np.pi * bx * by * np.sqrt(1 - brho**2))
    data = {"x": np.zeros((1, 2)), "y": np.zeros((1, 2)), "amplitude": bamp,
            "background": np.ones((1, 2)), "wx": bx, "wy": by, "rho": brho,
            "wx_err": np.full((1, 2), 0.01), "wy_err": np.full((1, 2), 0.01)}  # fmt: skip
    point = Traces(np.array([0.0, 50.0]), data).as_point_emitters(d_nm, px)
    np.testing.assert_allclose(point["wx"], wx, rtol=1e-12)
    np.testing.assert_allclose(point["wy"], wy, rtol=1e-12)
    np.testing.assert_allclose(point["rho"], rho, rtol=1e-12)
    np.testing.assert_allclose(point["amplitude"], amp, rtol=1e-12)
    np.testing.assert_allclose(point["wx_err"], 0.01 * bx / wx, rtol=1e-12)  # d(w²) kept
    narrow = Traces(np.array([0.0, 50.0]), {**data, "wx": np.array([[0.3, 2.0]])})
    assert not narrow.as_point_emitters(d_nm, px)["converged"][0, 0]  # narrower than the blur


@pytest.mark.slow
def test_cli_particle_nm_reaches_the_calibration(tmp_path):
    """`latentz calibrate --particle-nm 200` writes the calibration of the diameter given."""
    import tifffile
    from click.testing import CliRunner

    from latentz.cli import main

    stack = tmp_path / "beads.tif"
    tifffile.imwrite(stack, np.clip(_stack(BEAD_NM), 0, None).astype(np.uint16))
    out = tmp_path / "cal.h5"
    args = [stack, "--z-start", Z_NM[0], "--z-step", 25.0, "--offset", 100, "--gain", 1,
            "--readnoise", 1, "--pixel-size-nm", PX_NM, "--shape", "auto", "--roi-size", ROI,
            "--field-model", "nearest", "--particle-nm", BEAD_NM, "--out", out]  # fmt: skip
    result = CliRunner().invoke(main, ["calibrate", *map(str, args)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert Calibration.load(out).options["particle_diameter_nm"] == BEAD_NM

"""Aperture arrays: pixel size within 0.05 % with an honest uncertainty, and calibration through
focus like particles (Supp. Fig. 9)."""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from latentz.calibration.apertures import ApertureLattice

PITCH_NM, PIXEL_NM = 5000.0, 129.3


def _array(rng, *, rotation=0.3, noise=0.05, n_side=15, drop=0.1, spurious=3, kappa=0.0):
    """Square array about (300, 300) px with missing apertures and spurious detections."""
    i, j = (a.ravel() for a in np.meshgrid(*[np.arange(n_side) - n_side // 2] * 2, indexing="ij"))
    c, s, p = np.cos(rotation), np.sin(rotation), PITCH_NM / PIXEL_NM
    dx, dy = p * (c * j - s * i), p * (s * j + c * i)
    scale = 1 + kappa * (dx**2 + dy**2) / 300.0**2  # radial distortion about the centre
    x = 300 + dx * scale + rng.normal(0, noise, dx.size)
    y = 300 + dy * scale + rng.normal(0, noise, dx.size)
    keep = rng.uniform(size=x.size) > drop
    x = np.r_[x[keep], rng.uniform(0, 600, spurious)]
    y = np.r_[y[keep], rng.uniform(0, 600, spurious)]
    return x, y, keep.sum()


def test_recovers_pixel_size_rotation_and_rejects_spurious_points():
    x, y, n_real = _array(np.random.default_rng(0), rotation=1.0)
    fit = ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM)
    assert abs(fit.pixel_size_nm / PIXEL_NM - 1) < 5e-4
    assert abs(fit.pixel_size_nm - PIXEL_NM) < 4 * fit.pixel_size_err_nm
    # At 1 rad the lattice direction closest to +x is the other one, at 1 - pi/2 rad.
    assert fit.rotation_rad == pytest.approx(1.0 - np.pi / 2, abs=1e-3)
    assert abs(fit.anisotropy) < 1e-3 and abs(fit.shear_rad) < 1e-3
    assert fit.used[:n_real].all() and not fit.used[n_real:].any()
    # 2n - 6 degrees of freedom: the scatter estimate is within a few of its own standard errors.
    assert fit.sigma_px == pytest.approx(0.05, rel=4 / np.sqrt(2 * (2 * n_real - 6)))
    # Indices are a consistent lattice: neighbours in space differ by one index step.
    res = fit.residuals()[fit.used]
    assert np.sqrt(np.mean(res**2)) == pytest.approx(fit.sigma_px, rel=0.01)


@pytest.mark.parametrize("rotation", [0.0, 0.004, -0.3, np.pi / 4, 1.2, np.pi / 2 + 0.1])
def test_indexing_is_robust_to_rotation(rotation):
    x, y, n_real = _array(np.random.default_rng(4), rotation=rotation, drop=0.2, spurious=10)
    fit = ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM)
    assert abs(fit.pixel_size_nm - PIXEL_NM) < 4 * fit.pixel_size_err_nm
    assert fit.used.sum() == n_real
    folded = np.mod(fit.rotation_rad - rotation + np.pi / 4, np.pi / 2) - np.pi / 4
    assert abs(folded) < 1e-3  # the same lattice, up to the square's 4-fold symmetry


def test_uncertainty_is_honest_over_noise_draws():
    """(estimate - truth) / sigma has mean 0 and standard deviation 1 over repeated draws."""
    rng = np.random.default_rng(1)
    n_draws = 400
    pulls = np.empty(n_draws)
    for k in range(n_draws):
        x, y, _ = _array(rng)
        fit = ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM)
        pulls[k] = (fit.pixel_size_nm - PIXEL_NM) / fit.pixel_size_err_nm
    # Sampling errors: mean 1/sqrt(N) = 0.05, std 1/sqrt(2N) = 0.035; allow 4 of each.
    assert abs(np.mean(pulls)) < 4 / np.sqrt(n_draws)
    assert abs(np.std(pulls) - 1) < 4 / np.sqrt(2 * n_draws)


def test_distortion_field_models_the_residual_displacement():
    x, y, n_real = _array(
        np.random.default_rng(2), noise=0.02, n_side=11, drop=0.0, spurious=0, kappa=1e-2
    )
    plain = ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM)
    assert plain.distortion is None and plain.sigma_px > 5 * 0.02  # the lattice cannot fit it
    fit = ApertureLattice.from_estimate(
        x, y, pitch_nm=PITCH_NM, distortion_terms=15, field_shape=(600, 600)
    )
    assert fit.used.all()  # systematic distortion is not mistaken for outliers
    left = fit.distortion.residuals()
    # After the Zernike distortion field only the noise is left, shrunk by the fitted terms.
    expected = 0.02 * np.sqrt(1 - (fit.distortion.n_terms_effective[0] + 3) / n_real)
    assert np.sqrt(np.mean(left**2)) == pytest.approx(expected, rel=4 / np.sqrt(2 * n_real))
    np.testing.assert_allclose(fit.distortion(x, y), fit.residuals() - left, atol=1e-12)


def test_end_to_end_through_simulated_aperture_array():
    simulate = pytest.importorskip("latentz.simulate")
    from latentz.localization import localize

    ds = simulate.aperture_array(seed=0)
    locs = localize(ds.frames, camera=ds.camera)
    truth = ds.truth[["x", "y"]].to_numpy()
    dist, nearest = cKDTree(truth).query(locs[["x", "y"]].to_numpy())
    locs = locs.assign(aperture=nearest)[dist < 2.0]
    mean = locs.groupby("aperture")[["x", "y"]].mean()
    assert len(mean) >= 0.9 * len(truth)
    fit = ApertureLattice.from_estimate(
        mean["x"].to_numpy(), mean["y"].to_numpy(), pitch_nm=ds.pitch_nm
    )
    assert abs(fit.pixel_size_nm / ds.pixel_size_nm - 1) < 5e-4
    assert fit.rotation_rad == pytest.approx(ds.rotation_rad, abs=1e-3)


def test_errors():
    x, y, _ = _array(np.random.default_rng(3))
    with pytest.raises(ValueError, match="at least 4 aperture positions"):
        ApertureLattice.from_estimate(x[:3], y[:3], pitch_nm=PITCH_NM)
    with pytest.raises(ValueError, match="`y_px` to have shape"):
        ApertureLattice.from_estimate(x, y[:-1], pitch_nm=PITCH_NM)
    with pytest.raises(ValueError, match="`pitch_nm` to be finite and > 0"):
        ApertureLattice.from_estimate(x, y, pitch_nm=-5.0)
    with pytest.raises(ValueError, match="to be finite"):
        ApertureLattice.from_estimate(np.r_[x, np.nan], np.r_[y, 1.0], pitch_nm=PITCH_NM)
    with pytest.raises(ValueError, match="`field_shape` is required"):
        ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM, distortion_terms=10)
    line = np.arange(10.0) * 38.0
    with pytest.raises(ValueError, match="lattice"):
        ApertureLattice.from_estimate(line, 0 * line + 5, pitch_nm=PITCH_NM)
    fit = ApertureLattice.from_estimate(x, y, pitch_nm=PITCH_NM)
    with pytest.raises(ValueError, match=r"`indices` to have shape \(n, 2\)"):
        fit.predict(np.zeros((3, 3), int))


@pytest.fixture(scope="module")
def aperture_calibration():
    """Supp. Fig. 9's second array: sub-resolution apertures imaged through focus, calibrated
    like particles."""
    from latentz.calibration import calibrate
    from latentz.simulate import AberrationMap, aperture_array

    z = np.arange(-2000.0, 2001.0, 100.0)
    aberrations = AberrationMap.default(seed=4)
    ds = aperture_array(
        shape=(192, 192), z_nm=z, aberrations=aberrations, seed=4, origin=(700, 1500)
    )
    cal = calibrate(
        ds.frames,
        z,
        camera=ds.camera,
        field_model="nearest",
        roi_size=21,
        stage_offsets_px=[ds.origin[::-1]],
    )
    return ds, cal


def _noise_free_rho_zero(ds, field_x, field_y):
    """Piezo z at which the fitted ρ of a noise-free aperture image crosses zero."""
    from latentz.fit import fit_rois
    from latentz.simulate import render_spots

    z = np.arange(-600.0, 601.0, 10.0)
    cx, cy = int(np.rint(field_x)), int(np.rint(field_y))
    spots = pd.DataFrame(
        {"frame": np.arange(z.size), "x": field_x - cx + 10, "y": field_y - cy + 10, "z_nm": 0.0}
    )
    images, _ = render_spots(
        spots,
        frame_shape=(21, 21),
        origin=(cy - 10, cx - 10),
        z_piezo_nm=z,
        photons=2e4,
        diameter_nm=0.0,
        background=50.0,
        optics=ds.optics,
        aberrations=ds.aberrations,
        noise=False,
    )
    rho = fit_rois(images)["rho"].to_numpy()
    k = np.flatnonzero(np.diff(np.sign(rho)) != 0)[0]
    return z[k] - rho[k] * (z[k + 1] - z[k]) / (rho[k + 1] - rho[k])


def test_apertures_calibrate_like_particles_and_find_where_rho_a_is_zero(aperture_calibration):
    ds, cal = aperture_calibration
    assert len(cal.kept) == len(cal.culled) >= 0.9 * len(ds.truth)
    shift = cal.plane(*(cal.positions * cal.camera.pixel_size_nm).T)
    z_zero = cal.local_z(0.0) + shift  # back on the piezo axis
    # the inverse polynomial's error at one point: σ_z scaled by its parameters over the planes
    # it was fitted to (the model part of Calibration.apply's z_err_nm)
    model = cal.local.shapes["rho_A"]
    used = np.sum(np.isfinite(model.sigma_z), axis=1)
    sigma = cal.particles["sigma_z"].to_numpy() * np.sqrt((model.inverse.order + 1) / used)
    chosen = np.random.default_rng(0).choice(len(cal.kept), 5, replace=False)
    error = np.array([z_zero[i] - _noise_free_rho_zero(ds, *cal.positions[i]) for i in chosen])
    print(
        "z(ρ_A = 0) - noise-free ρ = 0 crossing (nm):", error.round(1), "σ", sigma[chosen].round(1)
    )
    # ρ_A = ρ / A_n crosses zero where ρ does
    assert np.all(np.abs(error) <= 3 * sigma[chosen])
    assert abs(error.mean()) <= 3 * np.sqrt(np.mean(sigma[chosen] ** 2) / chosen.size)


def test_figure_of_where_each_array_shows_rho_a_zero(aperture_calibration, tmp_path):
    from matplotlib.image import imread

    from latentz.calibration import figure_shape_zero

    _, cal = aperture_calibration
    path = tmp_path / "supp_fig9.png"
    fig = figure_shape_zero({"apertures": cal}, path=path)
    assert len(fig.axes) >= 2 and imread(path).shape[0] > 100

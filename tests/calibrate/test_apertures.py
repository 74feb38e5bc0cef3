"""Aperture-array lattice fit: pixel size within 0.05 % with an honest uncertainty."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from latentz.calibrate.apertures import ApertureLattice

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
    from latentz.localize import localize

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

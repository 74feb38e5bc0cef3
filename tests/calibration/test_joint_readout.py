"""The joint axial readout (:func:`latentz.calibration.readout.joint_z`) on analytic
astigmatic curves with known truth: spots drawn at known z with Gaussian noise of a known
covariance on (wx, wy, ρ). Its z must reach the Cramér–Rao bound of that noise, 1 / sqrt(Jᵀ C⁻¹
J) at the true z, its σ must cover about 68 % of the errors, and where the curves cannot tell the
two sides of focus apart (no astigmatism), σ must reach the mirror image."""

import numpy as np
import pytest

from latentz.calibration.readout import _quadratic, joint_z, profile_width, shape_covariance

N = 3000  # spots: a coverage's binomial standard error is sqrt(0.68 · 0.32 / N) ≈ 0.009
COVERAGE_TOL = 3 * np.sqrt(0.683 * 0.317 / N)
# RMS / bound: relative standard error 1 / sqrt(2N) ≈ 0.013; 4 of them, plus 0.03 for the
# curves' curvature over one σ (the noise is ~5 % of the widths: second-order bias)
RATIO_TOL = 4 / np.sqrt(2 * N) + 0.03
GRID = np.arange(-1000.0, 1000.1, 20.0)  # nm, the calibration planes
W0, DEPTH = 1.3, 400.0  # in-focus width (px) and focal depth (nm)


def _curves(gamma_nm: float):
    """An astigmatic Gaussian PSF's widths (foci at ±gamma_nm) and a ρ that is 0."""

    def curves_at(particle, z):
        z = np.broadcast_to(
            np.asarray(z, float), np.broadcast_shapes(np.shape(particle), np.shape(z))
        )
        return {
            "wx": W0 * np.sqrt(1 + ((z - gamma_nm) / DEPTH) ** 2),
            "wy": W0 * np.sqrt(1 + ((z + gamma_nm) / DEPTH) ** 2),
            "rho": np.zeros_like(z),
            **{f"{k}_scatter": np.zeros(np.shape(particle)) for k in ("wx", "wy", "rho")},
        }

    return curves_at


def _spots(curves_at, z_true: np.ndarray, rng: np.random.Generator):
    """Fitted (wx, wy, ρ) of spots at ``z_true`` with correlated noise, and its covariance."""
    sd = np.array([0.06, 0.06, 0.03])
    corr = np.array([[1.0, 0.6, 0.1], [0.6, 1.0, 0.1], [0.1, 0.1, 1.0]])
    cov = np.broadcast_to(sd[:, None] * corr * sd[None, :], (len(z_true), 3, 3)).copy()
    c = curves_at(np.zeros(len(z_true), int), z_true)
    mean = np.column_stack([c["wx"], c["wy"], c["rho"]])
    noise = rng.standard_normal((len(z_true), 3)) @ np.linalg.cholesky(cov[0]).T
    return mean + noise, cov


def _bound(curves_at, z: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """1 / sqrt(Jᵀ C⁻¹ J) at z, J from the analytic curves by central differences (1 nm)."""
    hi, lo = curves_at(np.zeros(len(z), int), z + 0.5), curves_at(np.zeros(len(z), int), z - 0.5)
    j = np.column_stack([hi[k] - lo[k] for k in ("wx", "wy", "rho")])
    return 1 / np.sqrt(np.einsum("ni,nij,nj->n", j, np.linalg.inv(cov), j))


def test_joint_z_reaches_its_bound_and_its_sigma_covers():
    rng = np.random.default_rng(3)
    curves_at = _curves(gamma_nm=300.0)
    z_true = rng.uniform(-600.0, 600.0, N)
    fitted, cov = _spots(curves_at, z_true, rng)
    out = joint_z(curves_at, GRID[None, :], np.zeros((1, 3)), np.zeros(N, int), fitted, cov)
    error = out.z_nm - z_true
    bound = _bound(curves_at, z_true, cov)
    assert np.sqrt(np.mean((error / bound) ** 2)) == pytest.approx(1.0, abs=RATIO_TOL)
    sigma = np.fmax(out.sigma_nm, out.spread_nm)
    assert np.mean(np.abs(error) < sigma) == pytest.approx(0.683, abs=COVERAGE_TOL)


def test_without_astigmatism_sigma_reaches_the_other_side_of_focus():
    """No astigmatism: z and −z give the same image, the readout cannot choose, and σ must span
    both (the reported z is right up to its sign)."""
    rng = np.random.default_rng(4)
    curves_at = _curves(gamma_nm=0.0)
    z_true = rng.choice([-1, 1], N) * rng.uniform(300.0, 700.0, N)
    fitted, cov = _spots(curves_at, z_true, rng)
    out = joint_z(curves_at, GRID[None, :], np.zeros((1, 3)), np.zeros(N, int), fitted, cov)
    sigma = np.fmax(out.sigma_nm, out.spread_nm)
    assert np.all(sigma >= 2 * np.abs(out.z_nm) - 2 * np.diff(GRID)[0])
    mirrored = np.fmin(np.abs(out.z_nm - z_true), np.abs(out.z_nm + z_true))
    bound = _bound(curves_at, z_true, cov)
    assert np.sqrt(np.mean((mirrored / bound) ** 2)) == pytest.approx(1.0, abs=RATIO_TOL)
    assert np.mean(np.abs(out.z_nm - z_true) < sigma) > 0.683 - COVERAGE_TOL


def test_without_astigmatism_the_profile_over_the_window_covers_68_percent():
    """No astigmatism: the curvature's σ, or the spread to the mirror image, spans the whole
    range and covers ~90 % of the errors of spots in range. Their true z lie in a window
    (-300 to 800 nm, the particle's range) and so, read inside it, do the spots: the 68 %
    half-width of the likelihood over the window's planes covers 68 % of them."""
    rng = np.random.default_rng(6)
    curves_at = _curves(gamma_nm=0.0)
    lo, hi = -300.0, 800.0
    z_true = rng.uniform(lo, hi, N)
    fitted, cov = _spots(curves_at, z_true, rng)
    p = np.zeros(N, int)
    out = joint_z(curves_at, GRID[None, :], np.zeros((1, 3)), p, fitted, cov)
    inside = (out.z_nm >= lo) & (out.z_nm <= hi)  # in range
    window = np.broadcast_to([lo, hi], (N, 2))
    width = profile_width(curves_at, GRID[None, :], np.zeros((1, 3)), p, fitted, cov, out.z_nm,
                          window)  # fmt: skip
    error = np.abs(out.z_nm - z_true)[inside]
    tol = 3 * np.sqrt(0.683 * 0.317 / inside.sum())
    assert np.mean(error < width[inside]) == pytest.approx(0.683, abs=tol)
    assert np.mean(error < np.fmax(out.sigma_nm, out.spread_nm)[inside]) > 0.85


def test_shape_covariance_from_errors_and_correlations():
    """The (wx, wy, ρ) block of the covariance built from a fit's errors and correlations."""
    params = np.array([[5.0, 5.0, 1000.0, 10.0, 1.4, 1.2, 0.1]])
    errors = np.array([[30.0, 0.05, 0.04, 0.02]])  # amplitude, wx, wy, ρ
    corr = np.array([[0.1, 0.2, 0.0, 0.6, -0.3, 0.25]])  # CORRELATED order
    cov = shape_covariance(params, errors, corr, roi_size=11, readnoise=1.0)[0]
    sd = errors[0, 1:]
    expected = np.array([[1, 0.6, -0.3], [0.6, 1, 0.25], [-0.3, 0.25, 1]]) * np.outer(sd, sd)
    np.testing.assert_allclose(cov, expected, rtol=1e-12)


def test_bright_spots_sigma_is_their_bound_between_planes():
    """Spots 10x brighter: σ (~2 nm) far below the planes' half step (10 nm). The best plane's
    distance, up to 10 nm of z, must neither widen σ nor count as the curves not holding the
    spot: σ is the bound and covers 68 %."""
    rng = np.random.default_rng(5)
    curves_at = _curves(gamma_nm=300.0)
    z_true = rng.uniform(-600.0, 600.0, N)
    fitted, cov = _spots(curves_at, z_true, rng)
    c = curves_at(np.zeros(N, int), z_true)
    mean = np.column_stack([c[k] for k in ("wx", "wy", "rho")])
    fitted, cov = mean + 0.1 * (fitted - mean), 0.01 * cov
    out = joint_z(curves_at, GRID[None, :], np.zeros((1, 3)), np.zeros(N, int), fitted, cov)
    bound = _bound(curves_at, z_true, cov)
    assert np.median(bound) < np.diff(GRID)[0] / 4
    assert np.median(out.sigma_nm / bound) == pytest.approx(1.0, abs=0.02)
    sigma = np.fmax(out.sigma_nm, out.spread_nm)
    assert np.mean(np.abs(out.z_nm - z_true) < sigma) == pytest.approx(0.683, abs=COVERAGE_TOL)


def test_each_plane_compared_at_the_spots_own_brightness_finds_its_z():
    """A dim spot's fit takes the core of its image, narrower than the bright particle's fit by
    more the farther it is from focus: here its widths are the curves' times
    1 − 0.3 (z / 1 µm)². Given that shift at every plane, the search finds the true z of
    noise-free spots 600–900 nm from focus; with the one shift read at 300 nm (where the
    shape value mimics them), it reads every one of them nearer focus by more than 4 of its
    σ."""
    curves_at = _curves(gamma_nm=300.0)
    z_true = np.array([600.0, 700.0, 800.0, 900.0])
    n = z_true.size

    def dim_minus_bright(z: np.ndarray) -> np.ndarray:
        c = curves_at(np.zeros(np.shape(z), int), z)
        core = -0.3 * (z / 1000.0) ** 2
        return np.stack([c["wx"] * core, c["wy"] * core, np.zeros(np.shape(z))], axis=-1)

    c = curves_at(np.zeros(n, int), z_true)
    fitted = np.column_stack([c["wx"], c["wy"], c["rho"]]) + dim_minus_bright(z_true)
    cov = np.broadcast_to(np.diag([0.06, 0.06, 0.03]) ** 2, (n, 3, 3)).copy()
    grid, scatter, p = GRID[None, :], np.zeros((1, 3)), np.zeros(n, int)
    by_plane = fitted[:, None, :] - dim_minus_bright(np.broadcast_to(GRID, (n, GRID.size)))
    found = joint_z(curves_at, grid, scatter, p, by_plane, cov, z_only=True).z_nm
    assert np.abs(found - z_true).max() <= 10.0  # half a plane
    one = fitted - dim_minus_bright(np.full(n, 300.0))
    wrong = joint_z(curves_at, grid, scatter, p, one, cov)
    assert np.all(z_true - wrong.z_nm > 4 * wrong.sigma_nm)
    # the same shift at every plane is the one shift
    same = np.broadcast_to(one[:, None, :], by_plane.shape)
    assert np.array_equal(
        joint_z(curves_at, grid, scatter, p, same, cov, z_only=True).z_nm,
        joint_z(curves_at, grid, scatter, p, one, cov, z_only=True).z_nm,
    )


def test_the_plane_distances_add_as_einsum_does():
    rng = np.random.default_rng(4)
    r = rng.normal(size=(50, 61, 3)) * 10 ** rng.uniform(-3, 3, size=(50, 61, 3))
    r[rng.random(r.shape) < 0.01] = np.nan
    weight = rng.normal(size=(50, 3, 3))
    weight = weight @ weight.transpose(0, 2, 1)
    expected = np.einsum("mki,mij,mkj->mk", r, weight, r)
    np.testing.assert_array_equal(_quadratic(r, weight), expected)  # to the last bit

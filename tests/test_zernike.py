"""Zernike basis: Noll's table, orthonormality by exact quadrature, stability at 400 terms."""

from math import factorial

import numpy as np
import pytest
from scipy.special import eval_jacobi

from latentz._shared.zernike import (
    field_to_disk,
    fit_zernike,
    lstsq_operator,
    noll_to_nm,
    press_terms,
    truncated_lstsq_operator,
    zernike_design,
    zernike_polar,
)

# Noll (1976), Table I: Z_j for j = 1 ... 15, written out by hand.
NOLL_TABLE = {
    1: lambda r, t: np.ones_like(r),
    2: lambda r, t: 2 * r * np.cos(t),
    3: lambda r, t: 2 * r * np.sin(t),
    4: lambda r, t: np.sqrt(3) * (2 * r**2 - 1),
    5: lambda r, t: np.sqrt(6) * r**2 * np.sin(2 * t),
    6: lambda r, t: np.sqrt(6) * r**2 * np.cos(2 * t),
    7: lambda r, t: np.sqrt(8) * (3 * r**3 - 2 * r) * np.sin(t),
    8: lambda r, t: np.sqrt(8) * (3 * r**3 - 2 * r) * np.cos(t),
    9: lambda r, t: np.sqrt(8) * r**3 * np.sin(3 * t),
    10: lambda r, t: np.sqrt(8) * r**3 * np.cos(3 * t),
    11: lambda r, t: np.sqrt(5) * (6 * r**4 - 6 * r**2 + 1),
    12: lambda r, t: np.sqrt(10) * (4 * r**4 - 3 * r**2) * np.cos(2 * t),
    13: lambda r, t: np.sqrt(10) * (4 * r**4 - 3 * r**2) * np.sin(2 * t),
    14: lambda r, t: np.sqrt(10) * r**4 * np.cos(4 * t),
    15: lambda r, t: np.sqrt(10) * r**4 * np.sin(4 * t),
}


@pytest.fixture(scope="module")
def polar_points():
    rng = np.random.default_rng(0)
    return np.sqrt(rng.uniform(0, 1, 500)), rng.uniform(-np.pi, np.pi, 500)


def _disk_quadrature(n_rho: int, n_theta: int):
    """Gauss-Legendre in rho (weight rho) x uniform theta, area element normalised by pi.

    Exact for r^k with k <= 2 n_rho - 2 and for trigonometric frequencies below n_theta.
    """
    nodes, weights = np.polynomial.legendre.leggauss(n_rho)
    rho, w_rho = (nodes + 1) / 2, weights / 2 * (nodes + 1) / 2
    theta = np.arange(n_theta) * 2 * np.pi / n_theta
    r, t = np.meshgrid(rho, theta, indexing="ij")
    w = np.outer(w_rho, np.full(n_theta, 2 * np.pi / n_theta)) / np.pi
    return r.ravel(), t.ravel(), w.ravel()


def test_noll_indices_follow_noll_1976():
    n, m = noll_to_nm(15)
    assert n.tolist() == [0, 1, 1, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 4]
    assert m.tolist() == [0, 1, -1, 0, -2, 2, -1, 1, -3, 3, 0, 2, -2, 4, -4]


def test_low_orders_match_noll_table(polar_points):
    rho, theta = polar_points
    z = zernike_polar(rho, theta, 15)
    for j, formula in NOLL_TABLE.items():
        np.testing.assert_allclose(z[:, j - 1], formula(rho, theta), atol=1e-13, err_msg=f"Z{j}")


def test_radial_recurrence_matches_factorial_sum_and_jacobi(polar_points):
    rho, _ = polar_points
    n, m = noll_to_nm(400)
    z = zernike_polar(rho, np.zeros_like(rho), 400)  # theta = 0: cos terms = radial x norm
    for col in np.flatnonzero(m >= 0):
        nn, mm = int(n[col]), int(m[col])
        norm = np.sqrt(nn + 1.0) if mm == 0 else np.sqrt(2.0 * (nn + 1))
        k = (nn - mm) // 2
        jacobi = (-1) ** k * rho**mm * eval_jacobi(k, mm, 0, 1 - 2 * rho**2)
        np.testing.assert_allclose(z[:, col] / norm, jacobi, atol=1e-11)
        if nn <= 10:  # the explicit sum is only trustworthy at low order
            explicit = sum(
                (-1) ** s
                * factorial(nn - s)
                / (factorial(s) * factorial((nn + mm) // 2 - s) * factorial((nn - mm) // 2 - s))
                * rho ** (nn - 2 * s)
                for s in range(k + 1)
            )
            np.testing.assert_allclose(z[:, col] / norm, explicit, atol=1e-12)


@pytest.mark.parametrize("n_terms", [15, 400])
def test_orthonormal_on_disk_by_exact_quadrature(n_terms):
    n_max = int(noll_to_nm(n_terms)[0].max())
    r, t, w = _disk_quadrature(n_max + 2, 2 * n_max + 8)
    z = zernike_polar(r, t, n_terms)
    assert np.all(np.isfinite(z))
    gram = (z * w[:, None]).T @ z
    np.testing.assert_allclose(gram, np.eye(n_terms), atol=1e-10)


def test_unit_circle_and_centre_values():
    z = zernike_polar(np.array([0.0, 1.0]), np.array([0.3, 0.0]), 400)
    n, m = noll_to_nm(400)
    # R_n^m(1) = 1, so at theta = 0 every cos/m=0 term equals its normalisation, sin terms 0.
    norm = np.where(m == 0, np.sqrt(n + 1.0), np.sqrt(2.0 * (n + 1)))
    np.testing.assert_allclose(z[1], np.where(m >= 0, norm, 0.0), atol=1e-10 * norm.max())
    # At the centre only m = 0 terms survive, with R_n^0(0) = (-1)^(n/2).
    np.testing.assert_allclose(z[0], np.where(m == 0, norm * (-1.0) ** (n // 2), 0.0), atol=1e-12)


def test_field_maps_into_disk_with_corners_on_circle():
    h, w = 60, 100
    x = np.array([(w - 1) / 2, -0.5, w - 0.5, -0.5, w - 0.5])
    y = np.array([(h - 1) / 2, -0.5, -0.5, h - 0.5, h - 0.5])
    rho, theta = field_to_disk(x, y, field_shape=(h, w))
    np.testing.assert_allclose(rho, [0, 1, 1, 1, 1], atol=1e-15)
    np.testing.assert_allclose(theta[1:], np.arctan2([-h, -h, h, h], [-w, w, -w, w]))


def test_fit_recovers_coefficients_exactly():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 127, 200), rng.uniform(0, 95, 200)
    truth = rng.normal(size=(28, 3))
    values = zernike_design(x, y, field_shape=(96, 128), n_terms=28) @ truth
    coef = fit_zernike(x, y, values, field_shape=(96, 128), n_terms=28)
    np.testing.assert_allclose(coef, truth, atol=1e-9)


def test_lstsq_operator_matches_numpy_lstsq():
    rng = np.random.default_rng(3)
    design = zernike_design(
        rng.uniform(0, 63, 80), rng.uniform(0, 63, 80), field_shape=(64, 64), n_terms=21
    )
    values = rng.normal(size=(80, 4))
    operator, condition = lstsq_operator(design)
    np.testing.assert_allclose(operator @ values, np.linalg.lstsq(design, values)[0], atol=1e-10)
    np.testing.assert_allclose(condition, np.linalg.cond(design), rtol=1e-10)


def test_truncated_operator_keeps_most_terms_within_condition_limit():
    rng = np.random.default_rng(4)
    x, y = rng.uniform(0, 99, 100), rng.uniform(0, 99, 100)
    design = zernike_design(x, y, field_shape=(100, 100), n_terms=66)
    conds = np.array([np.linalg.cond(design[:, :p]) for p in range(1, 67)])
    assert np.all(np.diff(conds) >= -1e-9 * conds[1:])  # non-decreasing, as the bisection needs
    limit = np.sqrt(conds[10] * conds[-1])  # somewhere between 11 and 66 terms
    expected = int(np.sum(conds <= limit))
    operator, condition, p = truncated_lstsq_operator(design, max_terms=66, max_condition=limit)
    assert p == expected and 11 <= p < 66
    np.testing.assert_allclose(condition, conds[p - 1], rtol=1e-8)
    np.testing.assert_allclose(operator, np.linalg.pinv(design[:, :p]), atol=1e-9)
    assert truncated_lstsq_operator(design, max_terms=0, max_condition=10.0)[2] == 0


def test_press_terms_minimises_naive_leave_one_out_error():
    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 63, 70), rng.uniform(0, 63, 70)
    values = np.column_stack([np.sin(x / 9.0) * np.cos(y / 13.0), np.exp(-((x - 30) ** 2) / 400)])
    values += rng.normal(0, 0.01, values.shape)
    design = zernike_design(x, y, field_shape=(64, 64), n_terms=36)
    press = {}
    for p in (1, 3, 6, 10, 15, 21, 28, 36):
        err = 0.0
        for i in range(70):
            keep = np.arange(70) != i
            coef = np.linalg.lstsq(design[keep, :p], values[keep])[0]
            err += np.sum((values[i] - design[i, :p] @ coef) ** 2)
        press[p] = err
    assert press_terms(design, values, max_terms=36) == min(press, key=press.get)
    assert press_terms(design, values, max_terms=0) == 0


def test_errors():
    with pytest.raises(ValueError, match="`rho` within the unit disk"):
        zernike_polar(np.array([1.5]), np.array([0.0]), 3)
    with pytest.raises(ValueError, match="`theta` to have shape"):
        zernike_polar(np.array([0.5]), np.array([0.0, 1.0]), 3)
    with pytest.raises(ValueError, match="`n_terms` to be >= 1"):
        noll_to_nm(0)
    with pytest.raises(ValueError, match="`x_px` within the field"):
        field_to_disk(np.array([10.0]), np.array([1.0]), field_shape=(8, 8))
    with pytest.raises(ValueError, match="`field_shape` to be"):
        field_to_disk(np.array([1.0]), np.array([1.0]), field_shape=8)
    with pytest.raises(ValueError, match="`y_px` to have shape"):
        field_to_disk(np.array([1.0]), np.array([1.0, 2.0]), field_shape=(8, 8))
    x = np.linspace(0, 7, 5)
    with pytest.raises(ValueError, match="at least `n_terms` = 10 points"):
        fit_zernike(x, x, x, field_shape=(8, 8), n_terms=10)
    with pytest.raises(ValueError, match="ill-conditioned"):  # collinear points
        fit_zernike(x, x, x, field_shape=(8, 8), n_terms=4)
    with pytest.raises(ValueError, match="`values` to have 5 rows"):
        fit_zernike(x, x, x[:4], field_shape=(8, 8), n_terms=2)
    with pytest.raises(ValueError, match="`values` to be finite"):
        fit_zernike(x, x, np.full(5, np.nan), field_shape=(8, 8), n_terms=2)

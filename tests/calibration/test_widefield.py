"""Widefield model on analytic fields: exact where the truth lies in the model's span, the grid
against per-spot evaluation, and the range rule (no extrapolation)."""

import numpy as np
import pytest

from latentz.calibration.fieldmodels import FieldModel
from latentz.calibration.widefield import WidefieldModel

SHAPE = (256, 256)
RNG = np.random.default_rng(7)
X, Y = RNG.uniform(2, 253, (2, 400))
S_GRID = np.linspace(-1.0, 1.0, 161)
Z_GRID = np.linspace(-2500.0, 2500.0, 201)


def _curv(x, y):
    u, v = (x - 128) / 128, (y - 128) / 128
    return 60.0 * (u**2 + v**2) + 20.0 * v


def _z(x, y, s):
    return 2000.0 * np.sin(s) + _curv(x, y)


def _dx(x, y, z):
    return 2e-4 * z * (x - 128) / 128


def _dy(x, y, z):
    return -1e-4 * z * (y - 128) / 128 + 0.05


def _model(kind, *, left_short=False):
    zt = _z(X[:, None], Y[:, None], S_GRID[None])
    if left_short:  # the left half of the field covers s <= 0.6 only
        zt[(X < 128)[:, None] & (S_GRID[None] > 0.6)] = np.nan
    dxt = _dx(X[:, None], Y[:, None], Z_GRID[None])
    dyt = _dy(X[:, None], Y[:, None], Z_GRID[None])
    return WidefieldModel.from_tables(
        X, Y, S_GRID, zt, Z_GRID, dxt, dyt, kind=kind, field_shape=SHAPE, n_terms=28
    )


@pytest.fixture(scope="module")
def zernike():
    return _model("zernike", left_short=True)


def test_grid_matches_exact_truth_within_the_issue_bounds(zernike):
    x, y = RNG.uniform(20, 236, (2, 2000))
    s = RNG.uniform(-0.9, 0.55, 2000)
    z, dx, dy, ok = zernike(x, y, s)
    assert ok.all()
    # linear interpolation of 2000 sin(s) on a step h = 0.0125: error <= h^2/8 * 2000 = 0.04 nm;
    # the curvature is in the span of 28 Zernike terms, so the fit adds only rounding
    assert np.max(np.abs(z - _z(x, y, s))) <= 0.1
    # lateral truth is linear in z: exact up to the z error times the slope (< 1e-4 px)
    assert np.max(np.abs(dx - _dx(x, y, z))) * 130 <= 0.5
    assert np.max(np.abs(dy - _dy(x, y, z))) * 130 <= 0.5


def test_grid_vs_exact_per_spot_fit(zernike):
    """Tabulated + interpolated vs a Zernike fit of the particles' exact z at each spot's s."""
    x, y = RNG.uniform(20, 236, (2, 30))
    s = RNG.uniform(-0.9, 0.55, 30)
    z, dx, dy, _ = zernike(x, y, s)
    exact = np.array(
        [
            FieldModel.from_estimate(
                X, Y, _z(X, Y, si), kind="zernike", field_shape=SHAPE, n_terms=28
            )(np.array([xi]), np.array([yi]))[0]
            for xi, yi, si in zip(x, y, s, strict=True)
        ]
    )
    assert np.max(np.abs(z - exact)) <= 2.0


def test_spots_beyond_what_nearby_particles_cover_are_out_of_range(zernike):
    x = np.array([40.0, 200.0, 40.0, 200.0])
    s = np.array([0.8, 0.8, 1.2, np.nan])
    z, dx, dy, ok = zernike(x, np.full(4, 128.0), s)
    assert ok.tolist() == [False, True, False, False]
    assert np.isnan(z[~ok]).all() and np.isnan(dx[~ok]).all() and np.isnan(dy[~ok]).all()
    assert zernike.s_range == (-1.0, 1.0)


@pytest.mark.parametrize("kind", ["natural", "nearest"])
def test_interpolants(kind):
    model = _model(kind)
    x, y = RNG.uniform(40, 216, (2, 500))
    s = RNG.uniform(-0.9, 0.9, 500)
    z, _, _, ok = model(x, y, s)
    assert ok.all()
    err = np.abs(z - _z(x, y, s))
    # natural neighbour reproduces the linear part exactly and the quadratic curvature to about
    # its second derivative times the squared spacing (~13 px): 120/128^2 * 13^2 ~ 1.2 nm;
    # nearest errs by the curvature's change over the spacing, (gradient <= 1.1 nm/px) x 13 px
    assert np.sqrt(np.mean(err**2)) <= (2.0 if kind == "natural" else 15.0)


def test_bad_options():
    with pytest.raises(ValueError, match="s_grid"):
        WidefieldModel.from_tables(
            X,
            Y,
            S_GRID[::-1].copy(),
            np.zeros((400, 161)),
            Z_GRID,
            np.zeros((400, 201)),
            np.zeros((400, 201)),
            kind="nearest",
            field_shape=SHAPE,
        )
    with pytest.raises(ValueError, match="min_fraction"):
        WidefieldModel.from_tables(
            X,
            Y,
            S_GRID,
            np.zeros((400, 161)),
            Z_GRID,
            np.zeros((400, 201)),
            np.zeros((400, 201)),
            kind="nearest",
            field_shape=SHAPE,
            min_fraction=2.0,
        )
    with pytest.raises(ValueError, match="iterations"):
        _model("nearest")(np.array([1.0]), np.array([1.0]), np.array([0.0]), iterations=-1)


def test_spots_beyond_the_field_are_out_of_range_not_errors():
    from latentz.calibration.widefield import WidefieldModel

    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 63, 80), rng.uniform(0, 63, 80)
    s_grid = np.linspace(-1, 1, 21)
    z_grid = np.linspace(-1000, 1000, 21)
    z_table = np.tile(1000 * s_grid, (80, 1))
    zeros = np.zeros((80, 21))
    model = WidefieldModel.from_tables(
        x,
        y,
        s_grid,
        z_table,
        z_grid,
        zeros,
        zeros,
        kind="zernike",
        field_shape=(64, 64),
        n_terms=6,
    )
    z, dx, dy, ok = model(
        np.array([10.0, 64.2, -3.0]), np.array([10.0, 10.0, 5.0]), np.array([0.5, 0.5, 0.5])
    )
    np.testing.assert_allclose(z[0], 500.0, atol=1e-6)
    assert ok.tolist() == [True, False, False] and np.isnan(z[1:]).all()

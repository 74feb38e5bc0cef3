"""PolyModel: batched scaled-Chebyshev least squares against analytic polynomials and NumPy."""

import warnings

import numpy as np
import pytest
from numpy.polynomial import Chebyshev, Polynomial
from numpy.polynomial.chebyshev import chebval

from latentz.calibration.polymodel import PolyModel

Z = np.linspace(-3000.0, 3000.0, 121)


def test_order16_in_nanometres_is_well_conditioned():
    # a 16th-order polynomial in raw nm: exact data must come back to rounding error
    rng = np.random.default_rng(1)
    truth = Polynomial(rng.normal(size=17), domain=[-3000, 3000], window=[-1, 1])
    model = PolyModel.from_estimate(Z, truth(Z), order=16)
    z_fine = np.linspace(-3000, 3000, 1001)
    assert np.max(np.abs(model(z_fine[None]) - truth(z_fine))) < 1e-9 * np.max(np.abs(truth(Z)))


def test_batch_with_masks_matches_one_by_one_fits():
    rng = np.random.default_rng(2)
    y = rng.normal(size=(5, Z.size)).cumsum(axis=1)
    mask = np.ones_like(y, dtype=bool)
    mask[1, :30] = False
    mask[3, 90:] = False
    y[2, 7] = np.nan  # non-finite points are ignored
    model = PolyModel.from_estimate(Z, y, order=6, mask=mask)
    for i in range(5):
        use = mask[i] & np.isfinite(y[i])
        ref = Chebyshev.fit(Z[use], y[i, use], 6)
        np.testing.assert_allclose(model[i](Z[None]), ref(Z)[None], rtol=1e-9, atol=1e-9)


def test_too_few_points_gives_invalid_row():
    y = np.vstack([Z * 2.0, Z * 3.0])
    mask = np.ones_like(y, dtype=bool)
    mask[1, 3:] = False  # 3 points for order 5
    model = PolyModel.from_estimate(Z, y, order=5, mask=mask)
    assert model.valid.tolist() == [True, False]
    assert np.all(np.isnan(model(np.zeros(2))[1:]))


def test_derivative_shift_contains_and_power_coefficients():
    y = 1e-9 * Z**3 - 2e-4 * Z + 5.0
    model = PolyModel.from_estimate(Z, y, order=3)
    z = np.array([[-1234.0, 0.0, 2500.0]])
    np.testing.assert_allclose(model.derivative()(z), 3e-9 * z**2 - 2e-4, rtol=1e-9)
    np.testing.assert_allclose(model.shifted([5.0])(z), 1e-9 * z**3 - 2e-4 * z, atol=1e-9)
    assert model.contains(np.array([[-3000.0, 3000.0, 3000.1]])).tolist() == [[True, True, False]]
    t = z / 3000.0  # scaled variable of the domain [-3000, 3000]
    power = model.coefficients()[0]
    np.testing.assert_allclose(np.polyval(power[::-1], t), model(z), rtol=1e-12)
    np.testing.assert_allclose(model.residuals(z, model(z)), 0.0, atol=1e-12)


def test_bad_input():
    with pytest.raises(ValueError, match="order"):
        PolyModel.from_estimate(Z, Z, order=-1)
    with pytest.raises(ValueError, match="domain"):
        PolyModel(np.zeros((2, 3)), np.zeros((3, 2)))
    model = PolyModel.from_estimate(Z, Z, order=1)
    with pytest.raises(ValueError, match="rows"):
        model(np.zeros(3))


def test_derivative_of_a_row_without_width_is_nan_without_a_warning():
    good = PolyModel.from_estimate(Z, 2e-4 * Z + 5.0, order=1)
    rows = PolyModel(np.vstack([good.coef, good.coef]), np.array([good.domain[0], [7.0, 7.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        slope = rows.derivative()(np.array([[0.0], [7.0]]))
    assert slope[0, 0] == pytest.approx(2e-4)
    assert np.isnan(slope[1, 0])


def test_leverage_is_how_much_each_residual_shrinks():
    """Residuals of a least-squares curve scatter by sqrt(1 − h) times the noise: measured over
    4,000 noise draws on uneven abscissae (dense at one end), against h."""
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.0, 1.0, 40) ** 2) * 600.0 - 300.0
    mask = np.ones((1, x.size), dtype=bool)
    mask[0, :3] = False  # points left out of the fit have no leverage
    noise = rng.normal(0.0, 1.0, (4000, x.size))
    model = PolyModel.from_estimate(x, noise, order=6, mask=mask)
    h = model[0].leverage(x[None], mask)[0]  # every row has the same points
    assert np.all(np.isnan(h[:3]))
    assert np.nansum(h) == pytest.approx(7.0)  # the trace of the hat matrix: its parameters
    spread = model.residuals(np.broadcast_to(x, noise.shape), noise)[:, 3:].std(axis=0)
    # each spread from 4,000 draws is known to 1/sqrt(8000) = 1.1 %
    np.testing.assert_allclose(spread, np.sqrt(1.0 - h[3:]), rtol=0.045)


@pytest.mark.parametrize("order", [2, 5, 16])
def test_evaluation_is_numpys_chebval_to_the_bit(order):
    """Each row's series at its own points, one point or many, rows without a model NaN: the
    same bits as NumPy's ``chebval`` of the row's coefficients at the scaled variable
    ``t = (2 x - lo - hi) / (hi - lo)`` of the class's docstring."""
    rng = np.random.default_rng(order)
    coef = rng.normal(size=(50, order + 1))
    coef[7] = np.nan
    domain = np.column_stack([rng.uniform(-900.0, 0.0, 50), rng.uniform(1.0, 900.0, 50)])
    model = PolyModel(coef, domain)
    for x in (rng.uniform(-1200.0, 1200.0, 50), rng.uniform(-1200.0, 1200.0, (50, 9))):
        got = model(x)
        expected = np.array(
            [
                chebval((2.0 * row - lo - hi) / (hi - lo), c)
                for c, (lo, hi), row in zip(coef, domain, x, strict=True)
            ]
        )
        assert got.shape == x.shape
        assert np.array_equal(got, expected, equal_nan=True)

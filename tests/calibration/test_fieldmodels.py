"""Field models: known fields recovered, leave-one-out against naive refits, masks, batching."""

import h5py
import numpy as np
import pytest
from metpy.interpolate import natural_neighbor_to_points

from latentz._shared.zernike import zernike_design
from latentz.calibration.fieldmodels import FIELD_MODEL_KINDS, FieldModel, field_errors

SHAPE = (96, 128)  # (H, W) pixels


def _smooth(x, y):
    return np.sin(x / 25.0) + np.cos(y / 31.0) + 1e-4 * x * y


def _particles(n, seed=0, shape=SHAPE):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, shape[1] - 0.5, n), rng.uniform(-0.5, shape[0] - 0.5, n)


def _masks(n, m, seed):
    """Validity like a tabulated calibration: each particle covers a contiguous run of columns."""
    rng = np.random.default_rng(seed)
    lo = rng.integers(0, m // 2, n)
    hi = rng.integers(m // 2, m + 1, n)
    cols = np.arange(m)
    return (cols >= lo[:, None]) & (cols < hi[:, None])


def test_zernike_exact_for_low_order_polynomial_field():
    x, y = _particles(120, seed=1)
    h, w = SHAPE
    # A cubic in x, y lies in the span of the first 10 Zernike polynomials (orders n <= 3).
    u, v = (x - (w - 1) / 2) / 80.0, (y - (h - 1) / 2) / 80.0
    cubic = 1.0 + 0.3 * u - 0.2 * v**2 + 0.5 * u * v - 0.1 * u**3 + 0.05 * u * v**2
    model = FieldModel.from_estimate(x, y, cubic, kind="zernike", field_shape=SHAPE, n_terms=10)
    assert model.n_terms_effective.tolist() == [10]
    np.testing.assert_allclose(model.residuals(), 0.0, atol=1e-12)
    qx, qy = _particles(300, seed=2)
    qu, qv = (qx - (w - 1) / 2) / 80.0, (qy - (h - 1) / 2) / 80.0
    truth = 1.0 + 0.3 * qu - 0.2 * qv**2 + 0.5 * qu * qv - 0.1 * qu**3 + 0.05 * qu * qv**2
    np.testing.assert_allclose(model(qx, qy), truth, atol=1e-11)


@pytest.mark.filterwarnings("ignore:Zernike field model:UserWarning")  # masks leave few particles
def test_zernike_matches_per_column_lstsq_with_masks():
    x, y = _particles(150, seed=3)
    rng = np.random.default_rng(4)
    values = rng.normal(size=(150, 12))
    valid = _masks(150, 12, seed=5)
    model = FieldModel.from_estimate(
        x,
        y,
        values,
        kind="zernike",
        field_shape=SHAPE,
        valid=valid,
        n_terms=45,
        term_selection="max",
    )
    design = zernike_design(x, y, field_shape=SHAPE, n_terms=45)
    for c in range(12):
        rows = valid[:, c]
        p = min(45, rows.sum() // 2)
        assert model.n_terms_effective[c] == p
        ref = np.linalg.lstsq(design[rows, :p], values[rows, c])[0]
        np.testing.assert_allclose(model.coefficients[:p, c], ref, atol=1e-9)
        np.testing.assert_array_equal(model.coefficients[p:, c], 0.0)


@pytest.mark.filterwarnings("ignore:Zernike field model:UserWarning")  # masks leave few particles
@pytest.mark.parametrize("kind", FIELD_MODEL_KINDS)
def test_batched_equals_per_column_and_masks_are_respected(kind):
    n, m = 70, 6
    x, y = _particles(n, seed=6)
    rng = np.random.default_rng(7)
    values = _smooth(x, y)[:, None] * np.arange(1, m + 1) + rng.normal(0, 0.01, (n, m))
    valid = _masks(n, m, seed=8)
    garbage = np.where(valid, values, 1e9)  # invalid entries must never be used
    opts = {"kind": kind, "field_shape": SHAPE, "n_terms": 15}
    if kind == "zernike":  # PRESS pools the columns of a pattern; "max" makes them independent
        opts["term_selection"] = "max"
    batch = FieldModel.from_estimate(x, y, garbage, valid=valid, **opts)
    qx, qy = _particles(40, seed=9)
    full = batch(qx, qy)
    resid = batch.residuals()
    cols = rng.integers(0, m, qx.size)
    pointwise = batch(qx, qy, columns=cols)
    for c in range(m):
        rows = valid[:, c]
        single = FieldModel.from_estimate(x[rows], y[rows], values[rows, c], **opts)
        np.testing.assert_allclose(full[:, c], single(qx, qy), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(resid[rows, c], single.residuals(), rtol=1e-12, atol=1e-12)
        assert np.all(np.isnan(resid[~rows, c]))
    np.testing.assert_allclose(pointwise, full[np.arange(qx.size), cols], rtol=1e-13, atol=1e-13)
    pairs = rng.integers(0, m, (qx.size, 2))
    np.testing.assert_allclose(
        batch(qx, qy, columns=pairs),
        full[np.arange(qx.size)[:, None], pairs],
        rtol=1e-13,
        atol=1e-13,
    )
    if kind == "zernike":  # a design shared between models gives the same values
        design = zernike_design(qx, qy, field_shape=SHAPE, n_terms=20)
        np.testing.assert_allclose(batch(qx, qy, design=design), full, rtol=1e-13, atol=1e-13)
        with pytest.raises(ValueError, match=r"`design` to have shape \(40, >= 15\)"):
            batch(qx, qy, design=design[:, :10])
    else:
        with pytest.raises(TypeError, match="`design` applies to Zernike models only"):
            batch(qx, qy, design=np.zeros((qx.size, 15)))
    assert np.nanmax(np.abs(full)) < 1e3


def test_natural_matches_metpy_and_is_nan_outside_hull():
    x, y = _particles(200, seed=10)
    values = _smooth(x, y)
    model = FieldModel.from_estimate(x, y, values, kind="natural", field_shape=SHAPE)
    qx, qy = _particles(1000, seed=11)
    ref = natural_neighbor_to_points(np.column_stack([x, y]), values, np.column_stack([qx, qy]))
    got = model(qx, qy)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    assert np.isnan(ref).sum() > 0  # some queries do lie outside the hull
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    # At a particle the interpolant returns its value (MetPy itself returns NaN there).
    np.testing.assert_allclose(model(x[:5], y[:5]), values[:5], rtol=1e-15)


def test_nearest_matches_brute_force():
    x, y = _particles(90, seed=12)
    values = _smooth(x, y)
    model = FieldModel.from_estimate(x, y, values, kind="nearest", field_shape=SHAPE)
    qx, qy = _particles(200, seed=13)
    d2 = (qx[:, None] - x) ** 2 + (qy[:, None] - y) ** 2
    np.testing.assert_array_equal(model(qx, qy), values[np.argmin(d2, axis=1)])


@pytest.mark.parametrize("kind", ["natural", "nearest"])
def test_leave_one_out_equals_naive_refit(kind):
    n = 80
    x, y = _particles(n, seed=14)
    values = _smooth(x, y)
    model = FieldModel.from_estimate(x, y, values, kind=kind, field_shape=SHAPE)
    naive = np.empty(n)
    for i in range(n):
        keep = np.arange(n) != i
        other = FieldModel.from_estimate(
            x[keep], y[keep], values[keep], kind=kind, field_shape=SHAPE
        )
        naive[i] = values[i] - other(x[i], y[i])[0]
    resid = model.residuals()
    np.testing.assert_array_equal(np.isnan(resid), np.isnan(naive))
    np.testing.assert_allclose(resid, naive, rtol=1e-10, atol=1e-12)
    if kind == "natural":
        assert np.isnan(resid).sum() > 0  # hull particles have no leave-one-out prediction


def test_zernike_leave_one_out_equals_naive_refit():
    x, y = _particles(60, seed=24)
    values = _smooth(x, y) + np.random.default_rng(25).normal(0, 0.05, 60)
    opts = {"kind": "zernike", "field_shape": SHAPE, "n_terms": 21, "term_selection": "max"}
    model = FieldModel.from_estimate(x, y, values, **opts)
    naive = np.empty(60)
    for i in range(60):
        keep = np.arange(60) != i
        other = FieldModel.from_estimate(x[keep], y[keep], values[keep], **opts)
        assert other.n_terms_effective[0] == 21
        naive[i] = values[i] - other(x[i], y[i])[0]
    np.testing.assert_allclose(model.residuals(leave_one_out=True), naive, rtol=1e-8, atol=1e-10)
    with pytest.raises(ValueError, match="`leave_one_out` must be True for 'nearest'"):
        FieldModel.from_estimate(x, y, values, kind="nearest", field_shape=SHAPE).residuals(
            leave_one_out=False
        )


def test_press_selection_is_honest_where_fit_residuals_are_not():
    """Many terms fit the particles better and the field between them far worse."""
    x, y = _particles(300, seed=26)
    rng = np.random.default_rng(27)
    values = _smooth(x, y) + rng.normal(0, 0.02, x.size)
    qx, qy = _particles(3000, seed=28)
    opts = {"kind": "zernike", "field_shape": SHAPE, "n_terms": 150}
    press = FieldModel.from_estimate(x, y, values, **opts)
    greedy = FieldModel.from_estimate(x, y, values, **opts, term_selection="max")
    assert press.n_terms_effective[0] < greedy.n_terms_effective[0] == 150

    def rms(a):
        return float(np.sqrt(np.mean(a**2)))

    true_press = rms(press(qx, qy) - _smooth(qx, qy))
    true_greedy = rms(greedy(qx, qy) - _smooth(qx, qy))
    assert rms(greedy.residuals()) < rms(press.residuals())  # fit residuals mislead...
    assert true_greedy > 3 * true_press  # ...the truth between particles says otherwise
    # Leave-one-out errors track the truth: the error between particles plus the noise.
    for model, truth in ((press, true_press), (greedy, true_greedy)):
        loo = rms(model.residuals(leave_one_out=True))
        assert 0.5 < loo / np.hypot(truth, 0.02) < 2.0


@pytest.mark.parametrize(("kind", "order"), [("nearest", 1.0), ("natural", 2.0)])
def test_interpolants_converge_with_density(kind, order):
    """Nearest-neighbour error falls as spacing h ~ n^-1/2, natural-neighbour as h^2."""
    qx, qy = np.random.default_rng(15).uniform(30, 90, (2, 300))
    errors = []
    for n in (150, 2400):
        x, y = _particles(n, seed=16)
        model = FieldModel.from_estimate(x, y, _smooth(x, y), kind=kind, field_shape=SHAPE)
        errors.append(np.sqrt(np.mean((model(qx, qy) - _smooth(qx, qy)) ** 2)))
    expected = (150 / 2400) ** (order / 2)  # 16x density: 1/4 (nearest), 1/16 (natural)
    assert errors[1] / errors[0] < 2.0 * expected


def test_zernike_reduces_terms_with_few_particles_and_warns():
    x, y = _particles(30, seed=17)
    values = np.column_stack([_smooth(x, y), _smooth(x, y)])
    valid = np.ones_like(values, bool)
    valid[10:, 1] = False  # column 1 keeps 10 particles
    with pytest.warns(UserWarning, match="2 of 2 column"):
        model = FieldModel.from_estimate(
            x, y, values, kind="zernike", field_shape=SHAPE, valid=valid, term_selection="max"
        )
    assert model.n_terms_effective.tolist() == [15, 5]
    with pytest.warns(UserWarning, match="Columns with 0 terms are NaN"):
        lonely = FieldModel.from_estimate(
            x[:1], y[:1], values[:1, 0], kind="zernike", field_shape=SHAPE
        )
    assert np.isnan(lonely(10.0, 10.0)).all()


@pytest.mark.filterwarnings("ignore:Zernike field model:UserWarning")  # masks leave few particles
@pytest.mark.parametrize("kind", FIELD_MODEL_KINDS)
def test_round_trip_through_hdf5_is_bit_identical(kind, tmp_path):
    x, y = _particles(60, seed=18)
    values = _smooth(x, y)[:, None] * [1.0, -2.0, 3.0]
    valid = _masks(60, 3, seed=19)
    model = FieldModel.from_estimate(
        x, y, values, kind=kind, field_shape=SHAPE, valid=valid, n_terms=21
    )
    arrays, options = model.as_arrays()
    path = tmp_path / "field.h5"
    with h5py.File(path, "w") as f:
        for key, arr in arrays.items():
            f[key] = arr
        f.attrs.update(options)
    with h5py.File(path, "r") as f:
        back = FieldModel.from_arrays({k: f[k][()] for k in f}, dict(f.attrs))
    qx, qy = _particles(50, seed=20)
    np.testing.assert_array_equal(back(qx, qy), model(qx, qy))
    np.testing.assert_array_equal(back.residuals(), model.residuals())
    assert back.kind == kind and back.field_shape == SHAPE


def test_field_errors_of_white_noise_under_nearest_neighbour():
    """LOO residual of iid noise is the difference of two draws: rms sqrt(2) sigma, kurtosis 0."""
    n, sigma = 3000, 2.0
    x, y = _particles(n, seed=21)
    rng = np.random.default_rng(22)
    values = rng.normal(0, sigma, (n, 2))
    model = FieldModel.from_estimate(x, y, values, kind="nearest", field_shape=SHAPE)
    table = field_errors(model, circle_radius_px=40.0)
    h, w = SHAPE
    inside = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2) <= 40.0
    assert table["n_square"].tolist() == [n, n]
    assert table["n_circle"].tolist() == [inside.sum()] * 2
    # Mutual nearest pairs make residuals correlated in pairs: allow 4 standard errors of sqrt(2 n).
    for region, count in (("square", n), ("circle", inside.sum())):
        rms = table[f"rms_{region}"].to_numpy()
        assert np.all(np.abs(rms / (np.sqrt(2) * sigma) - 1) < 4 / np.sqrt(count))
        k = table[f"kurtosis_{region}"].to_numpy()
        assert np.all(np.abs(k) < 4 * table[f"kurtosis_err_{region}"].to_numpy())
    resid = model.residuals()
    np.testing.assert_allclose(rms, np.sqrt(np.mean(resid[inside] ** 2, axis=0)))


def test_bad_input_errors():
    x, y = _particles(10, seed=23)
    v = _smooth(x, y)
    ok = {"kind": "nearest", "field_shape": SHAPE}
    with pytest.raises(ValueError, match="`kind` to be one of"):
        FieldModel.from_estimate(x, y, v, kind="cubic", field_shape=SHAPE)
    with pytest.raises(ValueError, match="`y_px` to have shape"):
        FieldModel.from_estimate(x, y[:5], v, **ok)
    with pytest.raises(ValueError, match="`values` to have 10 rows"):
        FieldModel.from_estimate(x, y, v[:5], **ok)
    with pytest.raises(ValueError, match="distinct particle positions"):
        FieldModel.from_estimate(np.r_[x, x[0]], np.r_[y, y[0]], np.r_[v, 0.0], **ok)
    with pytest.raises(ValueError, match="`x_px` within the field"):
        FieldModel.from_estimate(x + 200, y, v, **ok)
    with pytest.raises(ValueError, match="`x_px` and `y_px` to be finite"):
        FieldModel.from_estimate(np.r_[x, np.nan], np.r_[y, 1.0], np.r_[v, 0.0], **ok)
    with pytest.raises(ValueError, match="at least one particle"):
        FieldModel.from_estimate([], [], [], **ok)
    with pytest.raises(TypeError, match="`valid` to be boolean"):
        FieldModel.from_estimate(x, y, v, valid=np.ones(10), **ok)
    with pytest.raises(ValueError, match="`valid` to have the shape"):
        FieldModel.from_estimate(x, y, v, valid=np.ones(9, bool), **ok)
    with pytest.raises(ValueError, match="finite wherever `valid`"):
        FieldModel.from_estimate(x, y, np.r_[v[:9], np.nan], valid=np.ones(10, bool), **ok)
    with pytest.raises(ValueError, match="`field_shape` to be"):
        FieldModel.from_estimate(x, y, v, kind="nearest", field_shape=(96,))
    with pytest.raises(ValueError, match="`n_terms` to be >= 1"):
        FieldModel.from_estimate(x, y, v, kind="zernike", field_shape=SHAPE, n_terms=0)
    with pytest.raises(ValueError, match="`points_per_term` to be finite and > 0"):
        FieldModel.from_estimate(x, y, v, kind="zernike", field_shape=SHAPE, points_per_term=0)
    with pytest.raises(ValueError, match="`points_per_term` to be >= 1"):
        FieldModel.from_estimate(x, y, v, kind="zernike", field_shape=SHAPE, points_per_term=0.5)
    model = FieldModel.from_estimate(x, y, np.column_stack([v, v]), **ok)
    with pytest.raises(ValueError, match=r"`columns` in \[0, 1\], got 2"):
        model(x[:2], y[:2], columns=[0, 2])
    with pytest.raises(ValueError, match="`columns` to have 2 rows"):
        model(x[:2], y[:2], columns=[0])
    with pytest.raises(TypeError, match="`columns` to have a numeric dtype"):
        model(x[:2], y[:2], columns=[0.5, 1.0])
    with pytest.raises(ValueError, match="`y_px` within the field"):
        model(10.0, -3.0)
    assert np.isnan(model(np.nan, 5.0)).all()  # NaN positions pass through
    arrays, options = model.as_arrays()
    with pytest.raises(ValueError, match="Unsupported field-model format 99"):
        FieldModel.from_arrays(arrays, dict(options, format=99))
    with pytest.raises(ValueError, match="missing valid"):
        FieldModel.from_arrays({k: a for k, a in arrays.items() if k != "valid"}, options)
    with pytest.raises(ValueError, match="inconsistent shapes"):
        FieldModel.from_arrays(dict(arrays, x_px=arrays["x_px"][:3]), options)
    with pytest.raises(TypeError, match="`model` to be a FieldModel"):
        field_errors("zernike")
    with pytest.raises(ValueError, match="`circle_radius_px` to be finite and > 0"):
        field_errors(model, circle_radius_px=-1.0)


@pytest.mark.parametrize("kind", ["natural", "nearest", "zernike"])
def test_per_point_columns_equal_picking_from_every_column(kind):
    """Evaluating each point in its own columns (what apply does, with weights shared by the
    columns of one validity pattern) gives what evaluating every column and picking gives."""
    rng = np.random.default_rng(31)
    x, y = _particles(120, seed=30)
    values = np.column_stack([_smooth(x, y) * k for k in (1.0, 2.0, -1.0, 0.5)])
    valid = np.ones_like(values, dtype=bool)
    valid[:40, 1] = False  # columns 1 and 3 use other particles than columns 0 and 2
    valid[60:, 3] = False
    model = FieldModel.from_estimate(
        x, y, np.where(valid, values, 0.0), kind=kind, field_shape=SHAPE, valid=valid, n_terms=15
    )
    qx, qy = rng.uniform(10, SHAPE[1] - 10, 300), rng.uniform(10, SHAPE[0] - 10, 300)
    cols = rng.integers(0, 4, (300, 2))
    every = model(qx, qy)
    picked = np.take_along_axis(every, cols, axis=1)
    np.testing.assert_allclose(model(qx, qy, columns=cols), picked, rtol=1e-12, atol=1e-12)

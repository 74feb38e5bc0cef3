"""The field part of the reported errors (:func:`latentz.calibration.errors.field_sigma`) on
held-out tables of known make-up: a field error that grows in proportion to the distance, a
floor for a smoothing model, half the floor (the particles' own scatter, held twice in a held-out
error) for an interpolating one in z and the whole floor laterally, and the local models' part
that must not be counted twice."""

import numpy as np
import pandas as pd
import pytest

from latentz.calibration.errors import field_sigma

N = 4000  # held-out planes: the RMS of N normal errors has a relative standard error 1/sqrt(2N)
TOL = 4 / np.sqrt(2 * N) + 0.03  # 4 standard errors, plus the least-squares fit's own spread


def _table(model: str, floor_nm: float, per_px_nm: float, local_nm: float, seed: int):
    rng = np.random.default_rng(seed)
    distance = rng.uniform(5.0, 40.0, N)
    sd = np.sqrt(floor_nm**2 + (per_px_nm * distance) ** 2 + 2 * local_nm**2)
    return pd.DataFrame({"model": model, "particle": np.arange(N), "distance_px": distance,
                         "z_nm": rng.uniform(-900, 900, N), "in_range": True,
                         "err_z_nm": rng.normal(0.0, sd)})  # fmt: skip


@pytest.mark.parametrize("distance_px", [0.0, 10.0, 30.0])
def test_a_smoothing_model_has_a_floor_and_a_growth(distance_px):
    table = _table("zernike", floor_nm=20.0, per_px_nm=1.0, local_nm=0.0, seed=1)
    sigma = field_sigma(table, "zernike", "z", np.zeros(1), np.full(1, distance_px))
    assert sigma[0] == pytest.approx(np.hypot(20.0, distance_px), rel=TOL + 0.1)


@pytest.mark.parametrize("floor_nm", [0.0, 20.0])
def test_an_interpolating_model_adds_one_particles_scatter(floor_nm):
    """Held-out errors of an interpolating model hold two particles' scatter about the field
    (the held-out one's and its neighbour's), a spot only its neighbour's: half the floor."""
    table = _table("nearest", floor_nm=floor_nm, per_px_nm=1.5, local_nm=0.0, seed=2)
    d = np.array([0.0, 10.0, 30.0])
    sigma = field_sigma(table, "nearest", "z", np.zeros(3), d, bin_nm=2000.0)  # one z bin
    expected = np.sqrt(floor_nm**2 / 2 + (1.5 * d) ** 2)
    np.testing.assert_allclose(sigma[1:], expected[1:], rtol=TOL + 0.1)
    # at a particle, the floor alone: 4 standard errors of the least-squares intercept of
    # err² on d² (var err² = 2 sd⁴), halved
    d2 = table["distance_px"].to_numpy() ** 2
    sd2 = floor_nm**2 + 1.5**2 * d2
    lever = 1 / N - np.mean(d2) * (d2 - np.mean(d2)) / (N * np.var(d2))
    se = np.sqrt(np.sum(lever**2 * 2 * sd2**2))
    assert abs(sigma[0] ** 2 - floor_nm**2 / 2) <= 4 * se / 2


def test_the_local_models_part_is_not_counted_in_the_field_part():
    table = _table("nearest", floor_nm=0.0, per_px_nm=1.0, local_nm=20.0, seed=3)
    local = np.full(N, 20.0)
    with_local = field_sigma(table, "nearest", "z", np.zeros(1), np.full(1, 20.0))
    without = field_sigma(table, "nearest", "z", np.zeros(1), np.full(1, 20.0), model_nm=local)
    assert without[0] == pytest.approx(20.0, rel=TOL + 0.05)
    # counted in, it would be a floor of 2·20² nm², half of it added: sqrt(2) times as large
    assert with_local[0] > 1.3 * without[0]


def test_a_held_out_noise_that_a_spot_holds_elsewhere_is_taken_off_once():
    """Lateral held-out errors that also hold the held-out particle's own z noise carried
    through Δ (known per row, here 25 nm): the line is the field's alone."""
    table = _table("nearest", floor_nm=10.0, per_px_nm=1.0, local_nm=0.0, seed=5)
    noise = np.full(N, 25.0)
    err = np.hypot(table["err_z_nm"], np.random.default_rng(6).normal(0.0, noise))
    table = table.assign(err_x_nm=err * np.sign(table["err_z_nm"]))
    d = np.array([20.0])
    sigma = field_sigma(table, "nearest", "x", np.zeros(1), d, noise_nm=noise)
    assert sigma[0] == pytest.approx(np.hypot(10.0, 20.0), rel=TOL + 0.1)
    assert field_sigma(table, "nearest", "x", np.zeros(1), d)[0] > 1.3 * sigma[0]  # 1.5 counted


def test_lateral_errors_keep_the_whole_floor_and_are_not_extrapolated_below_the_held_out():
    """Laterally a particle has no offset of its own: a spot meets the whole floor, and below
    the nearest held-out distances (here 5 px, the 10th percentile ~8.5 px) the line is held."""
    table = _table("nearest", floor_nm=10.0, per_px_nm=1.0, local_nm=0.0, seed=4)
    table = table.rename(columns={"err_z_nm": "err_x_nm"})
    d10 = np.quantile(table["distance_px"], 0.1)
    d = np.array([0.0, d10, 30.0])
    sigma = field_sigma(table, "nearest", "x", np.zeros(3), d, bin_nm=2000.0)
    expected = np.sqrt(10.0**2 + (1.0 * np.maximum(d, d10)) ** 2)
    np.testing.assert_allclose(sigma, expected, rtol=TOL + 0.1)
    assert sigma[0] == sigma[1]
    z_sigma = field_sigma(table.rename(columns={"err_x_nm": "err_z_nm"}), "nearest", "z",
                          np.zeros(1), np.zeros(1), bin_nm=2000.0)  # fmt: skip
    assert z_sigma[0] < 0.8 * sigma[0]  # in z, half the floor and the line down to d = 0


def _bent_shift(z_nm: np.ndarray) -> np.ndarray:
    """A lateral correction Δx'(z) (px) that bends over ±1.5 µm."""
    return 0.3 * np.sin(z_nm / 500.0) + 0.1 * (z_nm / 1000.0) ** 2


@pytest.mark.parametrize(
    ("z_nm", "sigma_z_nm"), [(0.0, 20.0), (300.0, 100.0), (0.0, 800.0), (600.0, 3000.0)]
)
def test_the_z_error_reaches_the_lateral_error_through_the_curve_within_its_span(z_nm, sigma_z_nm):
    """σ of Δx'(z') − Δx'(z) for z' normal about z, held within the calibrated span (a spot in
    range lies there): truth by 4·10⁵ draws of z' through the curve itself. Where σ_z spans
    the curve, the slope times σ_z overstates it (weak astigmatism gives σ_z of microns)."""
    from latentz.calibration.errors import spread_through
    from latentz.calibration.polymodel import PolyModel

    grid = np.linspace(-1500.0, 1500.0, 61)
    model = PolyModel.from_estimate(grid, _bent_shift(grid), order=14)
    span = np.array([[-1500.0, 1500.0]])
    draws = np.clip(np.random.default_rng(0).normal(z_nm, sigma_z_nm, 400_000), *span[0])
    truth = np.sqrt(np.mean((_bent_shift(draws) - _bent_shift(np.array(z_nm))) ** 2))
    got = spread_through(model, np.array([z_nm]), np.array([sigma_z_nm]), span)[0]
    assert got == pytest.approx(truth, rel=0.02)
    if sigma_z_nm >= 800.0:
        slope = abs(model.derivative()(np.array([z_nm]))[0])
        assert slope * sigma_z_nm > 2 * truth


def _defect_field(x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """A lateral field error (nm) over a 256 px field: a gentle pattern of ±5 nm everywhere and
    six local defects, 8 px wide, where it reaches 60 nm."""
    centres = np.random.default_rng(7).uniform(20.0, 236.0, (6, 2))
    d2 = (x_px[:, None] - centres[:, 0]) ** 2 + (y_px[:, None] - centres[:, 1]) ** 2
    bumps = 60.0 * np.exp(-d2 / (2 * 8.0**2)).sum(axis=1)
    return 5.0 * np.sin(x_px / 7.0) * np.cos(y_px / 9.0) + bumps


@pytest.mark.parametrize(("axis", "model"), [("x", "nearest"), ("z", "zernike")])
def test_errors_with_a_heavy_tail_are_covered_as_a_normal_would_be(axis, model):
    """Held-out particles and, elsewhere, test emitters in a field whose error is a few nm
    everywhere and tens of nm at a few defects: the truth at each place is the field's value
    there. The mean square is ruled by the defects; a normal of that variance spans nearly every
    other error, so 1σ must be scaled to cover 68 % of the test emitters' errors, laterally and
    in z (a smoothing model, whose held-out errors are a spot's as they are)."""
    rng = np.random.default_rng(8)
    held = rng.uniform(0.0, 256.0, (N, 2))
    table = pd.DataFrame({"model": model, "particle": np.arange(N),
                          "distance_px": rng.uniform(5.0, 40.0, N),
                          "z_nm": rng.uniform(-900, 900, N), "in_range": True,
                          f"err_{axis}_nm": _defect_field(*held.T)})  # fmt: skip
    spots = rng.uniform(0.0, 256.0, (N, 2))
    truth = _defect_field(*spots.T)
    sigma = field_sigma(table, model, axis, rng.uniform(-900, 900, N),
                        rng.uniform(5.0, 40.0, N))  # fmt: skip
    covered = np.mean(np.abs(truth) <= sigma)
    assert 0.60 <= covered <= 0.76


@pytest.mark.parametrize(
    ("z_nm", "sigma_z_nm"), [(0.0, 20.0), (300.0, 100.0), (1000.0, 400.0), (600.0, 3000.0)]
)
def test_the_carried_z_error_covers_68_percent_where_the_curve_steepens(z_nm, sigma_z_nm):
    """With ``covering``, the width of Δx'(z') − Δx'(z) that holds 68.27 % of z' normal about
    z (within the span): truth by 4·10⁵ draws through the curve itself. Where the curve
    steepens towards its ends the root mean square is ruled by the few z' there and spans far
    more than 68 % of the differences."""
    from latentz.calibration.errors import spread_through
    from latentz.calibration.polymodel import PolyModel

    grid = np.linspace(-1500.0, 1500.0, 61)
    model = PolyModel.from_estimate(grid, _bent_shift(grid), order=14)
    span = np.array([[-1500.0, 1500.0]])
    draws = np.clip(np.random.default_rng(0).normal(z_nm, sigma_z_nm, 400_000), *span[0])
    differences = np.abs(_bent_shift(draws) - _bent_shift(np.array(z_nm)))
    truth = np.quantile(differences, 0.6827)
    args = (model, np.array([z_nm]), np.array([sigma_z_nm]), span)
    assert spread_through(*args, covering=True)[0] == pytest.approx(truth, rel=0.03)
    if z_nm >= 600.0:
        assert np.mean(differences <= spread_through(*args)[0]) > 0.74  # the RMS: too wide

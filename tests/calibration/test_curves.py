"""field_model="curves": each particle's own calibration curves, carried across the field.

Analytic traces (``calib_synthetic``) whose best focus varies linearly over the field: the
thin-plate spline of the curves at fixed z follows the shift to second order in the few nm it
changes between neighbours, so z of a spot between particles is right to within the local
models' own error, while the nearest particle errs by the gradient times the distance to it.
And traces whose astigmatism and best focus vary as waves about three particle spacings long:
there the curves carried by the spline keep z within a few nm where the nearest particle's
curve is off by tens.
"""

import numpy as np
import pandas as pd
import pytest
from calib_synthetic import make_traces, widths
from scipy.spatial import Delaunay

from latentz.calibration import calibrate_traces
from latentz.calibration.fieldmodels import field_weights
from latentz.calibration.widefield import _loo_smoothing, crossing

THETA = np.pi / 4
GRADIENT = np.array([0.3, -0.2])  # nm of best focus per px
N = 60


def _z_f(xy: np.ndarray) -> np.ndarray:
    return (xy - 250.0) @ GRADIENT


@pytest.fixture(scope="module")
def calibrations():
    rng = np.random.default_rng(3)
    positions = rng.uniform(0, 500, (N, 2))
    traces, _ = make_traces(N, z_f=_z_f(positions), positions=positions, noise=0.02, seed=2,
                            theta=THETA)  # fmt: skip
    opts = {"shape": "rho", "cull": False, "tilt": False}
    cal = {k: calibrate_traces(traces, field_model=k, **opts) for k in ("curves", "nearest")}
    return cal, positions


def _spots(xy: np.ndarray, z_nm: np.ndarray, z0: float) -> pd.DataFrame:
    """Spots at (x, y) whose images are those of a particle there at tilt-free z (nm)."""
    wx, wy, rho, s1, s2 = widths(z_nm + z0, _z_f(xy), theta=THETA)
    return pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1], "wx": wx, "wy": wy, "rho": rho,
                         "amplitude": 2e4 / (2 * np.pi * s1 * s2)})  # fmt: skip


@pytest.mark.slow
def test_curves_reproduce_a_linear_field_between_particles(calibrations):
    cal, positions = calibrations
    rng = np.random.default_rng(5)
    xy = rng.uniform(100, 400, (300, 2))
    xy = xy[Delaunay(positions).find_simplex(xy) >= 0]
    z = rng.uniform(-1000, 1000, len(xy))
    z0 = cal["curves"].plane.c0  # tilt=False: the flat focal plane at the particles' mean z_f
    rmse = {}
    for kind, c in cal.items():
        out = c.apply(_spots(xy, z, z0))
        assert out["in_range"].all()
        rmse[kind] = float(np.sqrt(np.mean((out["z_nm"] - z) ** 2)))
    # nearest errs by |gradient| x the distance to the nearest particle (~0.36 nm/px x ~20 px);
    # the curves only by their polynomials' residuals: a fraction of a nm at noise 0.02
    distance = np.min(np.hypot(*(xy[:, None, :] - positions[None]).transpose(2, 0, 1)), axis=1)
    expected_nearest = np.linalg.norm(GRADIENT) * np.sqrt(np.mean(distance**2))
    assert rmse["nearest"] > 0.5 * expected_nearest
    sigma_local = np.nanmedian(cal["curves"].particles["sigma_z"])
    assert rmse["curves"] < max(3 * sigma_local, 0.1 * expected_nearest)


@pytest.mark.slow
def test_curves_are_defined_over_the_whole_field(calibrations):
    cal, positions = calibrations
    lo, hi = positions.min(axis=0) + 0.5, positions.max(axis=0) - 0.5  # inside the field
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]])
    corners = corners[Delaunay(positions).find_simplex(corners) < 0]
    assert len(corners) >= 2  # the bounding box's corners outside the particles' hull
    z0 = cal["curves"].plane.c0
    out = cal["curves"].apply(_spots(corners, np.zeros(len(corners)), z0))
    assert out["in_range"].all()
    # outside the hull the weights are those of the nearest hull point: the error is at most the
    # gradient times the distance to the nearest particle
    distance = np.min(np.hypot(*(corners[:, None, :] - positions[None]).transpose(2, 0, 1)), 1)
    assert np.all(np.abs(out["z_nm"]) <= np.linalg.norm(GRADIENT) * distance + 1.0)


def test_curves_weights_are_natural_inside_the_hull_and_sum_to_one():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 100, (40, 2))
    queries = rng.uniform(-20, 120, (500, 2))
    inside = Delaunay(points).find_simplex(queries) >= 0
    q, p, w, ok = field_weights(points, queries, "curves")
    assert ok.all()
    np.testing.assert_allclose(np.bincount(q, w, minlength=len(queries)), 1.0, atol=1e-9)
    dense = np.zeros((len(queries), len(points)))
    np.add.at(dense, (q, p), w)
    qn, pn, wn, okn = field_weights(points, queries, "natural")
    natural = np.zeros_like(dense)
    np.add.at(natural, (qn, pn), wn)
    assert np.array_equal(okn, inside)
    np.testing.assert_allclose(dense[inside], natural[inside], atol=1e-9)
    # linear precision: the weights reproduce the positions themselves inside the hull
    np.testing.assert_allclose(dense[inside] @ points, queries[inside], atol=1e-6)


@pytest.mark.slow
def test_a_curves_calibration_round_trips(calibrations, tmp_path):
    from latentz.calibration import Calibration

    cal, positions = calibrations
    xy = positions[:10] + 3.0
    spots = _spots(xy, np.linspace(-800, 800, 10), cal["curves"].plane.c0)
    before = cal["curves"].apply(spots)
    cal["curves"].save(tmp_path / "cal.h5")
    loaded = Calibration.load(tmp_path / "cal.h5")
    assert loaded.field_model == "curves"
    pd.testing.assert_frame_equal(loaded.apply(spots), before)


def _wavy_c(xy: np.ndarray) -> np.ndarray:
    """Astigmatic half-separation (nm) that varies over ~4 particle spacings."""
    return 500 + 150 * np.sin(2 * np.pi * xy[:, 0] / 400) * np.cos(2 * np.pi * xy[:, 1] / 400)


def _wavy_z_f(xy: np.ndarray) -> np.ndarray:
    return 40 * np.sin(2 * np.pi * xy[:, 1] / 350)


@pytest.mark.slow
def test_curves_follow_aberrations_that_vary_between_particles():
    rng = np.random.default_rng(3)
    positions = rng.uniform(0, 500, (80, 2))  # ~56 px apart
    traces, _ = make_traces(80, z_f=_wavy_z_f(positions), positions=positions, noise=0.02,
                            seed=2, theta=THETA, c_nm=_wavy_c(positions))  # fmt: skip
    opts = {"shape": "rho", "cull": False, "tilt": False}
    cal = {k: calibrate_traces(traces, field_model=k, **opts) for k in ("curves", "nearest")}
    xy = rng.uniform(50, 450, (400, 2))
    xy = xy[Delaunay(positions).find_simplex(xy) >= 0]
    z = rng.uniform(-800, 800, len(xy))
    z0 = cal["curves"].plane.c0
    wx, wy, rho, s1, s2 = widths(z + z0, _wavy_z_f(xy), theta=THETA, c=_wavy_c(xy))
    spots = pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1], "wx": wx, "wy": wy, "rho": rho,
                          "amplitude": 2e4 / (2 * np.pi * s1 * s2)})  # fmt: skip
    rmse = {}
    for kind, c in cal.items():
        out = c.apply(spots)
        assert out["in_range"].mean() > 0.99
        rmse[kind] = float(np.sqrt(np.nanmean((out["z_nm"] - z) ** 2)))
    # nearest: ~40 nm; a Sibson-weighted mean of the neighbours' z(s): ~26 nm; the curves: ~7
    assert rmse["nearest"] > 20.0
    assert rmse["curves"] < 0.35 * rmse["nearest"]


def test_crossing_inverts_each_row_inside_its_bounds():
    grid = np.linspace(-1000.0, 1000.0, 201)
    slope = np.array([1e-3, -2e-3, 1e-3, 1e-3])
    curves = slope[:, None] * grid[None, :] + 0.5
    s = np.array([0.9, 0.1, 0.5, 0.9])
    lo = np.array([-1000.0, -1000.0, 10.0, -1000.0])
    hi = np.array([1000.0, 1000.0, 1000.0, 100.0])
    z = crossing(grid, curves, s, lo, hi)
    np.testing.assert_allclose(z[:2], (s[:2] - 0.5) / slope[:2])
    assert np.isnan(z[2])  # crosses at 0, below its bound
    assert np.isnan(z[3])  # crosses at 400, above its bound
    # a curve that turns back: the crossings inside the bounds only
    turn = np.abs(grid)[None, :] * 1e-3
    np.testing.assert_allclose(crossing(grid, turn, np.array([0.3]), np.array([0.0]),
                                        np.array([1000.0])), [300.0])  # fmt: skip


def test_surface_smoothing_is_chosen_by_leave_one_out():
    """A smooth field under per-particle scatter is smoothed; a field that changes between
    particles is interpolated exactly. The choice is checked against leave-one-out refits with
    scipy's own spline."""
    from scipy.interpolate import RBFInterpolator

    rng = np.random.default_rng(1)
    points = rng.uniform(0, 500, (60, 2))
    x, y = points.T
    smooth = np.column_stack([np.sin(x / 200), np.cos(y / 300), x * 1e-3])
    scattered = smooth + 0.05 * rng.standard_normal(smooth.shape)
    wavy = np.column_stack([np.sin(x / 40) * np.cos(y / 40), np.sin(y / 35)])
    assert _loo_smoothing(points, wavy) == 0.0
    chosen = _loo_smoothing(points, scattered)
    assert chosen > 0.0

    def refit_error(smoothing: float) -> float:
        errors = []
        for i in range(len(points)):
            rest = np.arange(len(points)) != i
            spline = RBFInterpolator(points[rest], scattered[rest], kernel="thin_plate_spline",
                                     smoothing=smoothing)  # fmt: skip
            errors.append(spline(points[i : i + 1])[0] - scattered[i])
        return float(np.mean(np.square(errors)))

    assert refit_error(chosen) < refit_error(0.0)
    # and the smoothed surface is nearer the field than the exact interpolant
    test = rng.uniform(50, 450, (400, 2))
    truth = np.column_stack([np.sin(test[:, 0] / 200), np.cos(test[:, 1] / 300), test[:, 0] * 1e-3])
    err = {
        s: np.sqrt(np.mean((RBFInterpolator(points, scattered, kernel="thin_plate_spline",
                                            smoothing=s)(test) - truth) ** 2))
        for s in (0.0, chosen)
    }  # fmt: skip
    assert err[chosen] < 0.8 * err[0.0]

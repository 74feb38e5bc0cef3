"""cal.evaluate(): widefield errors per field model against z, on a simulated calibration whose
local models are known to vary smoothly across the field."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def cal(small_zernike_calibration):
    """One calibration for the module: ``evaluate`` builds every field model it scores from the
    local models, whatever the calibration's own field model."""
    return small_zernike_calibration


def test_evaluate_reports_every_model_axis_and_region(cal):
    errors = cal.evaluate(n_z=9, n_s=11)
    assert set(errors["model"]) == {"zernike", "natural", "curves", "nearest"}
    assert set(errors["axis"]) == {"x", "y", "z"}
    for col in ("rms_square", "rms_circle", "kurtosis_square", "n_square"):
        assert col in errors
    lateral = errors[errors["axis"] != "z"].groupby("model")["rms_square"].median()
    # the lateral local models vary smoothly over the field: errors are a few nm, and the
    # nearest particle (which ignores the variation) is never better than natural neighbours
    assert lateral.max() < 20.0
    assert lateral["nearest"] >= lateral["natural"]
    assert lateral["nearest"] >= lateral["curves"]
    figures = cal.evaluate_figures(n_z=9, n_s=11)  # the default grid only adds columns
    assert len(figures) == 4 and "Cross-validated errors and reported uncertainties" in figures


def test_leave_one_out_of_the_interpolants_equals_a_refit_without_the_particle(cal):
    errors = cal.evaluate(kinds=("nearest",), n_z=3, n_s=3)
    # nearest neighbour, leave-one-out: each particle's error is its value minus its nearest
    # other particle's value; compute that directly for the middle z column of axis x
    from scipy.spatial import cKDTree

    kept = cal.kept
    x, y = cal.positions[kept].T
    z_mid = errors[(errors["axis"] == "x")]["z_nm"].iloc[1]
    dx, _ = cal.local_delta(z_mid)
    values = dx[kept] * cal.camera.pixel_size_nm
    _, idx = cKDTree(np.column_stack([x, y])).query(np.column_stack([x, y]), k=2)
    resid = values - values[idx[:, 1]]
    expected = np.sqrt(np.nanmean(resid**2))
    got = errors[(errors["axis"] == "x")]["rms_square"].iloc[1]
    np.testing.assert_allclose(got, expected, rtol=1e-9)


def test_field_errors_from_precomputed_residuals_are_the_same():
    import pandas as pd

    from latentz.calibration.fieldmodels import FieldModel, field_errors

    rng = np.random.default_rng(8)
    x, y = rng.uniform(0, 199, (2, 60))
    values = np.column_stack([np.sin(x / 40) + y / 100, np.cos(y / 30)])
    model = FieldModel.from_estimate(x, y, values, kind="natural", field_shape=(200, 200))
    pd.testing.assert_frame_equal(
        field_errors(model), field_errors(model, residuals=model.residuals())
    )

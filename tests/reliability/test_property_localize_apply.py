"""localize, calibrate and Calibration.apply under hostile input: each call returns a table whose
failures are flagged, or raises ValueError/TypeError; it never returns a silently wrong number."""

import warnings

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_property_fit import DTYPES, KINDS, make_rois

from latentz.calibration import calibrate
from latentz.localization import LOCALIZE_COLUMNS, localize


@given(
    kind=st.sampled_from(KINDS),
    dtype=st.sampled_from(DTYPES),
    t=st.integers(1, 3),
    h=st.integers(1, 48),
    w=st.integers(1, 48),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=30)
def test_localize_returns_flags_or_raises(kind, dtype, t, h, w, seed):
    frames = make_rois(kind, dtype, t, h, w, seed)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found = localize(frames, roi_size=7)
    except (ValueError, TypeError) as exc:
        assert str(exc)  # a message, naming the problem
        return
    assert list(found.columns) == list(LOCALIZE_COLUMNS)
    assert found["frame"].between(0, t - 1).all()
    good = found[found["converged"]]
    for column in ("x", "y", "wx", "wy", "x_err", "y_err", "photons"):
        assert np.isfinite(good[column]).all(), column
    assert ((good["x"] > -1) & (good["x"] < w) & (good["y"] > -1) & (good["y"] < h)).all()
    if kind in ("zero", "constant", "saturated"):
        assert not found["converged"].any()


@pytest.fixture(scope="module")
def cal(small_zernike_calibration):
    return small_zernike_calibration


FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(
    rows=st.lists(
        st.tuples(
            st.floats(-50, 450) | FLOATS,
            st.floats(-50, 450) | FLOATS,
            st.floats(0, 2e4) | FLOATS,
            st.floats(0.1, 12) | FLOATS,
            st.floats(0.1, 12) | FLOATS,
            st.floats(-0.99, 0.99) | FLOATS,
        ),
        min_size=0,
        max_size=20,
    )
)
@settings(max_examples=30)
def test_apply_flags_what_it_cannot_localize(cal, rows):
    spots = pd.DataFrame(rows, columns=["x", "y", "amplitude", "wx", "wy", "rho"], dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = cal.apply(spots)
    assert len(out) == len(spots)
    ok = out["in_range"].to_numpy(bool)
    for column in ("x_nm", "y_nm", "z_nm"):
        values = out[column].to_numpy(float)
        assert np.isfinite(values[ok]).all(), column
        assert np.isnan(values[~ok]).all(), column  # never a number for an unlocalizable spot
    bad_input = ~np.isfinite(spots.to_numpy()).all(axis=1)
    assert not ok[bad_input].any()
    # z never leaves the calibrated stack range (never extrapolated)
    span = cal.local.z_nm[cal.kept]
    assert (out["z_nm"][ok].between(np.nanmin(span) - 1e-6, np.nanmax(span) + 1e-6)).all()


def test_apply_refuses_tables_without_the_shape_columns(cal):
    with pytest.raises(ValueError, match="missing column"):
        cal.apply(pd.DataFrame({"x": [1.0], "y": [1.0]}))
    with pytest.raises(TypeError, match="DataFrame"):
        cal.apply(np.zeros((3, 6)))


@given(
    kind=st.sampled_from(("random", "zero", "constant", "nan", "saturated")),
    n_z=st.integers(1, 24),
    side=st.integers(1, 24),
    unsorted=st.booleans(),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=25)
def test_calibrate_gives_a_calibration_or_a_clear_error(kind, n_z, side, unsorted, seed):
    stack = make_rois(kind, np.float64, n_z, side, side, seed)
    z = np.arange(n_z) * 100.0
    if unsorted and n_z > 2:
        z[[0, 1]] = z[[1, 0]]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = calibrate(stack, z, field_model="nearest")
    except (ValueError, TypeError) as exc:
        assert str(exc)
        return
    # anything accepted from noise must flag its particles rather than invent a calibration
    assert len(result.culled) >= 1

"""The helpers that make the per-chunk work cheaper must give what NumPy and pandas give: medians
by sorting (`latentz._shared.medians`), columns set at once (`latentz._shared.columns`), and the
per-particle medians of the wrong-calibration check (`latentz.localization.mismatch`)."""

import numpy as np
import pandas as pd
import pytest

from latentz._shared.columns import with_columns
from latentz._shared.medians import _SAMPLE, row_medians, row_medians_and_mads


@pytest.mark.parametrize("n", [1, 2, 3, 64, 65, 4096, 4097])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_row_medians_and_their_absolute_deviations_are_numpys_in_float64(n, dtype):
    rng = np.random.default_rng(n)
    rows = [rng.normal(100, 20, n), rng.integers(95, 105, n), np.full(n, 7.0)]  # ties, constant
    heavy = rng.normal(100, 5, n)
    heavy[:: max(1, n // 10)] = 60000  # bright outliers, as spots in a noise sample
    values = np.clip(np.stack([*rows, heavy]), 0, 65535).astype(dtype)
    got = row_medians(values)
    assert got.dtype == np.float64
    assert np.array_equal(got, [np.median(row.astype(np.float64)) for row in values])
    centre, mads = row_medians_and_mads(values)
    assert np.array_equal(centre, got)
    deviations = np.abs(values.astype(np.float64) - got[:, None])
    assert np.array_equal(mads, [np.median(row) for row in deviations])


@pytest.mark.parametrize("row", [[3.0, np.nan, 1.0, 2.0], [np.nan, 4.0, np.nan], [np.nan, np.nan]])
def test_medians_and_deviations_of_rows_with_nan_are_those_of_two_sorts(row):
    values = np.array([row], np.float32)
    centre, mads = row_medians_and_mads(values)
    expected = row_medians(values)
    assert np.array_equal(centre, expected, equal_nan=True)
    deviations = np.abs(values.astype(np.float64) - expected[:, None])
    assert np.array_equal(mads, row_medians(deviations), equal_nan=True)


@pytest.mark.parametrize(
    "kind", ["noise sample", "sorted", "strided outliers", "grid", "cauchy", "ties"]
)
def test_selected_medians_and_deviations_of_long_rows_are_numpys(kind):
    """Rows long enough for `row_medians_and_mads`' narrowing steps, including rows whose strided
    sample misleads them (the steps fall back to sorting) and rows of a few distinct values."""
    rng = np.random.default_rng(7)
    n = 65536
    row = rng.normal(0.0, 3.0, n)
    if kind == "noise sample":
        row[rng.integers(0, n, 300)] = rng.uniform(50, 5000, 300)  # spots in a band-passed frame
    elif kind == "sorted":
        row = np.sort(row)
    elif kind == "strided outliers":  # the first step's sample far above the rest
        row[:: (n // _SAMPLE) | 1] = 1e6
    elif kind == "grid":  # a 2-D sample whose first column alone is wide, as a frame's edge
        row.reshape(256, 256)[:, 0] *= 30.0
    elif kind == "cauchy":
        row = rng.standard_cauchy(n)
    else:
        row = rng.integers(0, 4, n).astype(np.float64)
    for width in (n, n - 1):  # even and odd counts
        values = np.stack([row, row[::-1]]).astype(np.float32)[:, :width]
        centre, mads = row_medians_and_mads(values)
        assert np.array_equal(centre, [np.median(r.astype(np.float64)) for r in values])
        deviations = np.abs(values.astype(np.float64) - centre[:, None])
        assert np.array_equal(mads, [np.median(r) for r in deviations])


def test_with_columns_replaces_in_place_appends_in_order_and_keeps_index_and_attrs():
    table = pd.DataFrame({"a": [1.0, 2.0, 3.0], "b": [4, 5, 6], "c": [True, False, True]},
                         index=[7, 7, 2])  # fmt: skip
    table.attrs["roi_size"] = 11
    new = {"z": np.array([0.5, 0.6, 0.7]), "b": np.array([9, 8, 7]), "y": np.zeros(3, bool)}
    got = with_columns(table, new)
    expected = table.copy()
    for name, values in new.items():
        expected[name] = values
    pd.testing.assert_frame_equal(got, expected, check_exact=True)
    assert got.attrs == {"roi_size": 11}
    assert table.columns.tolist() == ["a", "b", "c"]  # the input is left as it was
    assert table["b"].tolist() == [4, 5, 6]


def test_with_columns_that_only_appends_leaves_the_input_as_it_was():
    table = pd.DataFrame({"a": [1.0, 2.0], "b": [3, 4]}, index=[5, 6])
    got = with_columns(table, {"c": np.array([0.1, 0.2])})
    assert got.columns.tolist() == ["a", "b", "c"] and got.index.tolist() == [5, 6]
    got.loc[5, "a"] = -1.0
    assert table.columns.tolist() == ["a", "b"] and table["a"].tolist() == [1.0, 2.0]


def test_particle_medians_are_each_particles_nanmedian_and_count():
    from latentz.localization.mismatch import _particle_medians

    rng = np.random.default_rng(3)
    particle = rng.integers(0, 12, 300) * 7  # not 0, 1, 2, ...: ascending order is kept
    values = rng.normal(0.0, 1.0, 300)
    values[rng.random(300) < 0.2] = np.nan
    values[particle == 14] = np.nan  # a particle whose every value is missing
    median, size = _particle_medians(values, particle)
    keys = np.unique(particle)
    assert np.array_equal(size, [np.sum(particle == k) for k in keys])
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning, match="All-NaN"):
        expected = [np.nanmedian(values[particle == k]) for k in keys]
    assert np.array_equal(median, expected, equal_nan=True)
    assert np.isnan(median[keys == 14]).all() and np.isfinite(median[keys != 14]).all()

"""fit_rois under hostile ROIs: every call either raises ValueError/TypeError with a message, or
returns one row per ROI in which a converged fit is physically meaningful and a degenerate ROI
(NaN, inf, all-zero, constant, saturated) is never reported as converged."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from latentz.fit import FIT_COLUMNS, fit_rois

DTYPES = (np.uint8, np.uint16, np.float32, np.float64)
KINDS = ("random", "nan", "inf", "zero", "constant", "saturated", "spot")


def make_rois(kind, dtype, n, h, w, seed):
    rng = np.random.default_rng(seed)
    top = float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else 1e6
    if kind == "random":
        rois = rng.uniform(0, min(top, 1e4), (n, h, w))
    elif kind == "spot":
        y, x = np.mgrid[:h, :w]
        spot = 200 * np.exp(-((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / (2 * 1.3**2))
        rois = rng.poisson(np.broadcast_to(10 + spot, (n, h, w))).astype(float)
    else:
        value = {"nan": np.nan, "inf": np.inf, "zero": 0.0, "constant": 7.0, "saturated": top}
        rois = np.full((n, h, w), value[kind])
    if np.issubdtype(dtype, np.integer):
        rois = np.clip(np.nan_to_num(rois, nan=0.0, posinf=top), 0, top)
    return rois.astype(dtype)


@given(
    kind=st.sampled_from(KINDS),
    dtype=st.sampled_from(DTYPES),
    n=st.integers(1, 4),
    h=st.integers(1, 41),
    w=st.integers(1, 41),
    seed=st.integers(0, 2**16),
)
def test_fit_rois_returns_flags_or_raises(kind, dtype, n, h, w, seed):
    rois = make_rois(kind, dtype, n, h, w, seed)
    if min(h, w) < 3:
        with pytest.raises(ValueError, match="at least 3 x 3"):
            fit_rois(rois)
        return
    fit = fit_rois(rois)
    assert list(fit.columns)[: len(FIT_COLUMNS)] == list(FIT_COLUMNS)
    assert len(fit) == n
    degenerate = kind in ("zero", "constant", "saturated") or (
        kind in ("nan", "inf") and not np.issubdtype(dtype, np.integer)
    )
    if degenerate:
        assert not fit["converged"].any(), fit
    if kind == "spot" and min(h, w) >= 9 and dtype != np.uint8:
        assert fit["converged"].all(), fit
    good = fit[fit["converged"]]
    for column in ("x", "y", "wx", "wy", "x_err", "y_err", "photons"):
        assert np.isfinite(good[column]).all(), column
    assert ((good["x"] > -1) & (good["x"] < w) & (good["y"] > -1) & (good["y"] < h)).all()
    assert ((good["wx"] > 0) & (good["wy"] > 0) & (good["rho"].abs() < 1)).all()


@pytest.mark.parametrize(
    ("rois", "error", "match"),
    [
        (np.zeros((0, 7, 7)), ValueError, "non-empty"),
        (np.zeros((7, 7)), ValueError, "rois"),
        (np.zeros((1, 7, 7), dtype=complex), (ValueError, TypeError), "rois"),
        ("not an array", (ValueError, TypeError), "rois"),
    ],
)
def test_fit_rois_bad_containers(rois, error, match):
    with pytest.raises(error, match=match):
        fit_rois(rois)

"""FRC against its expected value for emitters of known precision and number of localizations.

For emitters at uniform random places, each localized K times in each half with a Gaussian error
sigma, the two halves' transforms at frequency q correlate as
FRC(q) = K e^-a / (1 + (K - 1) e^-a), a = 4 pi^2 sigma^2 q^2,
so FRC = 1/7 at q = sqrt(ln(6K + 1)) / (2 pi sigma): the expected resolution is
2 pi sigma / sqrt(ln(6K + 1)) (4.50 sigma for K = 1). Binning into pixels adds p^2/12 to sigma^2
(2 % at 5 nm pixels and sigma 8 nm)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import latentz as lz
from latentz.analysis.resolution import frc_halves


def _emitters(rng, *, sigma: float, k: int, n_emitters: int = 20_000, field: float = 8000.0):
    """Each emitter localized k times in even frames and k times in odd frames."""
    where = rng.uniform(0, field, (n_emitters, 2))
    emitter = np.repeat(np.arange(n_emitters), 2 * k)
    frame = 2 * rng.integers(0, 5000, emitter.size) + np.tile(np.repeat([0, 1], k), n_emitters)
    xy = where[emitter] + rng.normal(0, sigma, (emitter.size, 2))
    return pd.DataFrame({"frame": frame, "x_nm": xy[:, 0], "y_nm": xy[:, 1]})


@pytest.mark.parametrize("seed", range(4))
def test_frc_resolution_matches_its_expected_value(seed):
    """Random precision (6-25 nm) and localizations per emitter (1-3 per half): within 20 % of
    the expected value (the requirement; the ring-sampling error of the crossing is ~3 %)."""
    rng = np.random.default_rng(seed)
    sigma, k = rng.uniform(6, 25), int(rng.integers(1, 4))
    result = lz.frc(_emitters(rng, sigma=sigma, k=k), pixel_nm=5.0, split="odd_even")
    expected = 2 * np.pi * sigma / np.sqrt(np.log(6 * k + 1))
    assert result.resolution_nm == pytest.approx(expected, rel=0.20)
    assert float(result) == result.resolution_nm
    curve = result.curve
    assert curve["frc"].iloc[0] > 0.9  # the coarse structure agrees between halves
    result.figure()


def test_block_halves_are_balanced_and_whole_blocks():
    frames = np.arange(10_000)
    side = frc_halves(frames, "blocks", n_blocks=20, seed=1)
    assert side.sum() == 5000
    # a block (500 consecutive frames) goes to one side
    assert np.all(side.reshape(20, 500).std(axis=1) == 0)


def test_too_few_localizations_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 100"):
        lz.frc(pd.DataFrame({"frame": [0, 1], "x_nm": [0.0, 1.0], "y_nm": [0.0, 1.0]}))

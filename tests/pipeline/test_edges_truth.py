"""Molecules at the frame's edge against truth, on random astigmatic microscopes each calibrated
with defaults on its own simulated 100 nm beads (:func:`latentz.validation.molecules.
edge_errors`): found, flagged ``edge``, good, and their x, y and z within the reported 1σ as
often as a right 1σ is. Truth is where the simulation put each molecule."""

import numpy as np
import pytest

from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import bead_calibration, edge_errors

pytestmark = pytest.mark.slow  # 33 s alone, two calibrations; ~10 s once numba has compiled


@pytest.fixture(scope="module")
def errors():
    """Two microscopes (not those the truncation terms were fitted on), 30 frames each: 720
    molecules 0–7.5 px from the border, 240 inside."""
    tables = []
    for seed in (131, 132):
        rng = np.random.default_rng(seed)
        microscope = random_microscope(rng)
        calibration = bead_calibration(microscope, seed)
        tables.append(edge_errors(microscope, calibration, rng, n_frames=30))
    return np.concatenate([t.to_records(index=False) for t in tables])


def test_molecules_at_the_edge_are_found_flagged_and_good(errors):
    near = errors[errors["distance_px"] < 7.5]
    assert len(near) == 720
    # detection misses about 1 % of those within 1 px of the border (their band-passed noise is
    # 1.56x the interior's), ~1 of these; 5 is the Poisson 99.9 % point of 1
    assert np.sum(~near["found"]) <= 5
    found = near[near["found"]]
    assert found["edge"][found["distance_px"] < 1].all()
    # good drops only the few whose z is not measured (out of range): 2 % in the benchmark
    assert found["good"].mean() >= 0.96


def test_errors_within_3_px_of_the_edge_are_within_their_1_sigma_68_percent_of_the_time(errors):
    """Where the edge cuts into the PSF (0–3 px), the fit must neither hide its truncation error
    nor overstate it: x (across and along the edge) and z within the reported 1σ 68.3 % of the
    time, within the sampling error of ~280 molecules over the two microscopes."""
    seen = errors[errors["found"] & np.isfinite(errors["z_nm"])]
    chosen = seen[seen["distance_px"] < 3.0]
    spread = 2.6 * np.sqrt(0.683 * 0.317 / len(chosen))  # 2.6 binomial SE: 0.072 at 280
    for axis in ("across", "along", "z"):
        covered = np.mean(np.abs(chosen[f"{axis}_nm"]) < chosen[f"{axis}_err_nm"])
        assert abs(covered - 0.683) < spread, (axis, covered, len(chosen))


@pytest.mark.parametrize("band", [(3.0, 7.5), (7.5, np.inf)])
def test_errors_farther_in_cover_within_the_per_microscope_band(errors, band):
    """From 3 px in, the PSF is nearly whole and coverage is the calibration's matter (72–78 %
    inside on these two microscopes): it must lie in the 50–85 % band that every microscope of
    the validation family is held to."""
    seen = errors[errors["found"] & np.isfinite(errors["z_nm"])]
    chosen = seen[(seen["distance_px"] >= band[0]) & (seen["distance_px"] < band[1])]
    for axis in ("across", "along", "z"):
        covered = np.mean(np.abs(chosen[f"{axis}_nm"]) < chosen[f"{axis}_err_nm"])
        assert 0.50 <= covered <= 0.85, (band, axis, covered)

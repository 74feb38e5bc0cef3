"""Dim molecules (300–1,000 photons) against truth, on a random astigmatic microscope calibrated
with defaults on its own simulated beads (:func:`latentz.validation.molecules.
precision_against_bounds`): detection, and x, y, z precision against the Cramér–Rao bound of
the five-parameter model (:func:`latentz.validation.bounds.localization_bounds`). Truth is where
the simulation put each molecule."""

import numpy as np
import pandas as pd
import pytest

from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import bead_calibration, precision_against_bounds

pytestmark = pytest.mark.slow  # 85 s alone (three calibrations, numba compiling); ~25 s warm


@pytest.fixture(scope="module")
def dim():
    """Three microscopes (not bench_dim's), 20 frames each: ~600 isolated molecules."""
    tables = []
    for seed in (141, 142, 143):
        rng = np.random.default_rng(seed)
        microscope = random_microscope(rng)
        calibration = bead_calibration(microscope, seed)
        tables.append(precision_against_bounds(
            microscope, calibration, rng, n_frames=20, photons=(300.0, 1000.0),
            z_range_nm=(-400.0, 400.0), yardsticks=True,
        ))  # fmt: skip
    errors = pd.concat(tables, ignore_index=True)
    return errors[errors["isolated"].to_numpy()]


def test_dim_molecules_are_found(dim):
    above = dim["photons"].to_numpy() >= 500
    # every one above 500 photons (bench_dim: 99–100 %); 2.6 binomial SE of 99 % over ~300
    spread = 2.6 * np.sqrt(0.01 * 0.99 / above.sum())
    assert dim["found"][above].mean() >= 0.99 - spread
    # 300-500 photons: 98.8 % found in bench_dim; 2.6 binomial SE of 97 % over ~250 is 2.8 %
    # (a threshold on the band-passed frame's own spread, which the molecules widen, found 90 %)
    below = ~above
    assert dim["found"][below].mean() >= 0.97 - 2.6 * np.sqrt(0.97 * 0.03 / below.sum())


@pytest.mark.parametrize("axis, most", [("x", 1.5), ("y", 1.5), ("z", 2.0)])
def test_dim_precision_lies_between_the_bound_and_its_known_loss(dim, axis, most):
    """No estimator beats the bound; latentz's x, y reach it within 20 % and its z within 1.4–1.7x
    (bench_dim: it fits seven parameters where the bound knows the curves, and a molecule is not
    the calibration's bead), so 1.5x and 2x are the limits."""
    seen = dim[np.isfinite(dim["z_nm"])]
    ratio = (seen[f"{axis}_nm"] / seen[f"{axis}_crlb_nm"]).to_numpy()
    robust = 1.4826 * np.median(np.abs(ratio))
    # the robust spread's sampling error is about 1.17 / sqrt(2 n) of it
    floor = 1.0 - 2.6 * 1.17 / np.sqrt(2 * len(ratio))
    assert floor <= robust <= most, (axis, robust, len(ratio))


def test_dim_z_errors_are_within_their_1_sigma_at_least_68_percent_of_the_time(dim):
    """The reported σ_z is not understated for dim molecules; it errs on the safe side (72–76 %
    over bench_dim's microscopes, 78 % over these three)."""
    seen = dim[np.isfinite(dim["z_nm"])]
    covered = np.mean(np.abs(seen["z_nm"]) < seen["z_err_nm"])
    spread = 2.6 * np.sqrt(0.683 * 0.317 / len(seen))  # 2.6 binomial SE (~500 molecules)
    assert 0.683 - spread <= covered <= 0.80, (covered, len(seen))


def test_a_fit_of_z_through_the_curves_takes_back_little_of_the_distance(dim):
    """The yardstick that fits z itself through the curves (``z_curves_nm``) spreads 0.87-1.02x
    as much as latentz's readout (robust; bench_dim's bands, 0.86 here): the readout wastes
    little, and the rest of the distance to the bound is the Gaussian model's. With the sign of
    the spot's brightness shift flipped, the yardstick spread 1.3-2.5x as much in bench_dim."""
    both = dim[np.isfinite(dim["z_nm"]) & np.isfinite(dim["z_curves_nm"])]

    def robust(column: str) -> float:
        return float(1.4826 * np.median(np.abs(both[column] / both["z_crlb_nm"])))

    ratio = robust("z_curves_nm") / robust("z_nm")
    assert 0.75 <= ratio <= 1.1, (ratio, len(both))


@pytest.mark.parametrize("axis, most", [("x", 1.4), ("y", 1.4), ("z", 1.6)])
def test_dim_precision_lies_near_the_bound_of_the_microscopes_own_psf(dim, axis, most):
    """Against the physical bound (the simulated microscope's own PSF, ``*_psf_crlb_nm``), which
    is not the Gaussian's: bench_dim puts x at 0.94-1.18x and z at 1.12-1.38x it (robust; x, y, z
    1.05, 1.26, 1.36 here)."""
    seen = dim[np.isfinite(dim["z_nm"]) & np.isfinite(dim[f"{axis}_psf_crlb_nm"])]
    ratio = (seen[f"{axis}_nm"] / seen[f"{axis}_psf_crlb_nm"]).to_numpy()
    robust = 1.4826 * np.median(np.abs(ratio))
    floor = 1.0 - 2.6 * 1.17 / np.sqrt(2 * len(ratio))
    assert floor <= robust <= most, (axis, robust, len(ratio))

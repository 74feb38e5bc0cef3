"""A calibration whose astigmatism lies 45° off, on weakly and very weakly astigmatic
microscopes, against truth.

Beads of the same microscope with its astigmatism turned by 45° calibrate it; its point
molecules (10³–10⁴ photons, within ±400 nm, 6 frames) are localized with that calibration and
with the right one. The turned calibration costs z (its RMSE against the simulated molecules
grows from 115 to 205 nm on the weak microscope, from 154 to 216 nm on the very weak one), yet
the spots' ellipticity against the calibration's at the z it reads turns by only +11° ± 6° and
+10° ± 6°, and their width ratio stays below its limit: neither sees it. Turning the calibration's
curves until they fit the spots best, each spot at its own best z, finds the 45° (−42.5° ± 1.4°,
−40° ± 1.5°), and the χ² that turn gains is 10 and 8 standard errors beyond zero, where the
right calibrations gain 1 and 1 (``benchmarks/results/bench_wrong_calibration.md``).
"""

from __future__ import annotations

import warnings
from functools import cache

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from latentz._shared.sanity import LatentzWarning
from latentz.localization.mismatch import check_calibration_fits
from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import with_calibration_of

pytestmark = pytest.mark.slow

#: Microscope seed and RMS astigmatism (nm) of each kind, as in bench_wrong_calibration.py.
MICROSCOPES = {"weak": (112, (20.0, 30.0)), "very weak": (13, (3.0, 8.0))}


@cache
def _localized(kind: str, calibration_of: str):
    """Molecules of the ``kind`` microscope localized with the beads of ``calibration_of``, the
    calibration, the simulated molecules and the microscope's pixel size (nm)."""
    seed, astigmatism = MICROSCOPES[kind]
    microscope = random_microscope(np.random.default_rng(seed), astigmatism_nm=astigmatism)
    locs, truth, calibration = with_calibration_of(microscope, calibration_of, seed)
    return locs, calibration, truth, microscope.optics.pixel_size_nm


def _z_errors(locs: pd.DataFrame, truth: pd.DataFrame, pixel_nm: float) -> pd.Series:
    """z error (nm) of the converged, unique, in-range spots, indexed by the nearest simulated
    molecule of their frame within 250 nm laterally (one spot per molecule), after their median
    z offset."""
    spots = locs[locs["converged"] & ~locs["duplicate"] & locs["in_range"]]
    errors = []
    for frame, rows in spots.groupby("frame"):
        molecules = truth[truth["frame"] == frame]
        distance, nearest = cKDTree(molecules[["x", "y"]].to_numpy()).query(
            rows[["x", "y"]].to_numpy()
        )
        near = distance * pixel_nm <= 250.0
        dz = rows["z_nm"].to_numpy()[near] - molecules["z_nm"].to_numpy()[nearest[near]]
        errors.append(pd.Series(dz, index=molecules.index[nearest[near]]))
    dz = pd.concat(errors)
    dz = dz[~dz.index.duplicated()]
    return dz - dz.median()


def _z_rmse_ratio(turned: pd.Series, right: pd.Series) -> float:
    """RMS z error of the turned calibration over the right one's, on the molecules both
    found: the same molecules, so that the dim ones only one of them finds do not weigh."""
    both = turned.index.intersection(right.index)
    return float(np.sqrt(np.mean(turned[both] ** 2) / np.mean(right[both] ** 2)))


@pytest.mark.parametrize("kind", MICROSCOPES)
def test_a_calibration_turned_45_degrees_is_caught_where_it_costs_z(kind):
    right, _, truth, pixel_nm = _localized(kind, "right")
    turned, turned_calibration, _, _ = _localized(kind, "axis 45° off")
    errors = (_z_errors(locs, truth, pixel_nm) for locs in (turned, right))
    assert _z_rmse_ratio(*errors) > 1.3
    assert not turned["good"].any()
    with pytest.warns(LatentzWarning, match="other axes"):  # what localize said, said again
        check_calibration_fits(turned, turned_calibration)


@pytest.mark.parametrize("kind", MICROSCOPES)
def test_the_right_calibration_is_not_condemned(kind):
    locs, calibration, _, _ = _localized(kind, "right")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="The calibration does not fit")
        assert check_calibration_fits(locs, calibration) is locs

"""`latentz.localization.quality`: one verdict per spot. Duplicates and unresolved pairs on tables
whose truth
is built in; consistency with the calibration on the real fit3Dcspline bead (its own odd-plane
calibration fits its even planes; the SMLM 2016 calibration, from another microscope, does not,
as it is and rotated by 45°)."""

import re
import warnings

import numpy as np
import pandas as pd
import pytest
from realdata import FIT3D_CAMERA, SMLM_CAMERA, fit3d_bead, score_z, smlm_beads

import latentz as lz
from latentz._shared.sanity import LatentzWarning
from latentz.localization.quality import UNRESOLVED_PX, assess, good_rows, summary


def _table(points, frame=0, error=0.05, converged=True):
    points = np.asarray(points, float)
    n = len(points)
    return pd.DataFrame(
        {
            "frame": np.full(n, frame),
            "x": points[:, 0],
            "y": points[:, 1],
            "x_err": np.broadcast_to(error, n).astype(float),
            "y_err": np.broadcast_to(error, n).astype(float),
            "converged": np.broadcast_to(converged, n),
        }
    )


def test_detections_on_one_emitter_are_merged_into_the_most_precise():
    # emitters at (20, 20) and (60, 20); the first detected three times, fits 0.1-0.4 px apart
    spots = _table([(20, 20), (20.3, 20.1), (60, 20), (19.9, 20.2)], error=[0.2, 0.05, 0.1, 0.3])
    out = assess(spots)
    assert out["duplicate"].tolist() == [True, False, False, True]
    assert out["good"].tolist() == [False, True, True, False]
    # the same points in another frame are another emitter
    both = pd.concat([spots, _table([(20, 20)], frame=1)], ignore_index=True)
    assert not assess(both)["duplicate"].iloc[-1]


def test_emitters_closer_than_the_unresolved_distance_are_unresolved():
    near, far = UNRESOLVED_PX - 0.5, UNRESOLVED_PX + 0.5  # in x; the distance is max(|dx|, |dy|)
    out = assess(_table([(20, 20), (20 + near, 21), (40, 40), (40 + far, 41)]))
    assert out["unresolved"].tolist() == [True, True, False, False]
    assert out["good"].tolist() == [False, False, True, True]


def test_unconverged_spots_are_not_good_and_not_anyones_neighbour():
    out = assess(_table([(20, 20), (23, 20)], converged=[True, False]))
    assert out["good"].tolist() == [True, False] and not out["unresolved"].any()
    kept, line = good_rows(out)
    assert len(kept) == 1 and "dropped 1" in line and "not converged 1" in line


@pytest.mark.realdata
def test_own_calibration_fits_the_even_planes():
    stack, z = fit3d_bead()
    cal = lz.calibrate(stack[1::2], z[1::2], camera=lz.Camera(**FIT3D_CAMERA))
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="The calibration does not fit")
        locs = lz.localize(stack[0::2], calibration=cal)
    checked = locs[np.isfinite(locs["consistency_chi2"]) & ~locs["duplicate"]]
    # χ² at its 99.9 % point: on ~100 spots a few flags at most are chance
    assert checked["inconsistent"].mean() <= 0.05
    # good spots lie where the calibration measures z well, and there z is right: against the
    # piezo z of these planes (never seen by the calibration), less one offset (latentz's z = 0
    # is the bead's focus), within 2x the measured plane-to-plane precision (3.6 / 3.3 nm)
    good = locs[locs["good"]]
    assert len(good) >= 30
    score = score_z(good["z_nm"], z[0::2][good["frame"].to_numpy()])
    assert score["rms"] <= 2 * score["jitter"], score


@pytest.fixture(scope="module")
def smlm_calibration():
    stack, z = smlm_beads()
    return lz.calibrate(stack, z, camera=lz.Camera(**SMLM_CAMERA))


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("angle", [0, 45])
def test_another_microscopes_calibration_ends_with_one_warning(smlm_calibration, angle):
    from scipy.ndimage import rotate

    stack, _ = fit3d_bead()
    if angle:
        stack = rotate(stack, angle, axes=(1, 2), reshape=False, mode="nearest")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        locs = lz.localize(stack, calibration=smlm_calibration, camera=lz.Camera(**FIT3D_CAMERA))
    messages = [str(w.message) for w in caught if issubclass(w.category, LatentzWarning)]
    assert len(messages) == 1 and "does not fit these data" in messages[0], messages
    # the cause: the bead's widths fall short of the calibration's (0.76x at the calibration
    # beads' photons: a blur far beyond a bead's); rotated, its astigmatism lies at 45°
    assert re.search(r"other axes" if angle else r"by a blur of \d+ nm", messages[0])
    assert summary(locs)["good"] <= 0.1 * len(locs)

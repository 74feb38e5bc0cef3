"""The verdicts on a real bead: the fit3Dcspline bead, whole and rotated by 45° then cropped to
15 px, calibrated with defaults on its odd planes and localized on its even ones. Truth is the
piezo z, with one offset removed (the median error of the planes within ±500 nm, as the SMLM
challenge removes one): no latentz fit enters it."""

import warnings

import numpy as np
import pytest
from realdata import FIT3D_CAMERA, fit3d_bead

import latentz as lz

pytestmark = pytest.mark.realdata


def _rotated_crop(stack):
    from scipy.ndimage import rotate

    return rotate(stack, 45, axes=(1, 2), reshape=False, mode="nearest")[:, 3:18, 3:18]


@pytest.mark.parametrize("prepare", [np.asarray, _rotated_crop], ids=["whole", "rotated-15px"])
def test_every_plane_within_500_nm_is_good_and_z_is_right(prepare):
    stack, z = fit3d_bead()
    stack = prepare(stack)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one bead: no tilt, nearest model, its ROI, its noise
        cal = lz.calibrate(stack[1::2], z[1::2], camera=lz.Camera(**FIT3D_CAMERA))
        locs = lz.localize(stack[0::2], calibration=cal)
    true_z = z[0::2]
    near = np.abs(true_z) <= 500  # 51 planes
    # one row per plane: the most precise fit that is not a duplicate
    best = locs[~locs["duplicate"]].sort_values("z_err_nm").drop_duplicates("frame")
    best = best[near[best["frame"].to_numpy()]]
    good = best[best["good"]]
    # ≥ 95 % of the 51 planes: at most 2 planes lost
    assert len(good) >= 0.95 * near.sum(), (len(good), near.sum())
    error = good["z_nm"].to_numpy() - true_z[good["frame"].to_numpy()]
    error -= np.median(error)
    # measured: 3.9 nm whole, 3.6 nm rotated and cropped (z RMSE after one offset)
    assert np.sqrt(np.mean(error**2)) <= 5.0
    # 1σ covers 60–76 %, within one sampling error of 51 planes (6.5 %): measured 70.6 % whole,
    # 76.5 % rotated (39 of 51 planes; the plane at +500 nm, now found, moves the median offset)
    coverage = np.mean(np.abs(error) <= good["z_err_nm"].to_numpy())
    sampling = np.sqrt(0.683 * 0.317 / len(good))
    assert 0.60 - sampling <= coverage <= 0.76 + sampling, coverage

"""Issue 13's Show on real data, defaults only (no shape, ROI, field model or method given):
the fit3Dcspline bead calibrates on its odd planes and localizes its even planes within ±500 nm;
the SMLM 2016 AS bead stack calibrates. Truth is the piezo z of the even planes, less one
constant: latentz puts z = 0 at the calibration bead's focus (:func:`realdata.score_z`).

The bead is calibrated with its documented camera (0.1 e-/ADU), although its pixels vary
between planes far less than that gain implies (background: 0.3-0.5x their mean in ADU,
against 10x for Poisson light at 0.1 e-/ADU; frames averaged, or another gain). The bead's own
calibration images then scatter about their z(s) curve, image by image, 0.77x (21 px) / 0.63x
(15 px crop) as much as their fit errors say, less far from focus than near it:
`Calibration.noise_scale_by_z` scales the fit's part of z_err_nm by that about each z where the
factor over all z is significantly below 1, and calibrate warns where it is below 1/sqrt(2)."""

import warnings

import numpy as np
import pandas as pd
import pytest
from realdata import FIT3D_CAMERA, SMLM_CAMERA, fit3d_bead, need, score_z, smlm_beads

import latentz as lz
from latentz._shared.sanity import LatentzWarning
from latentz.calibration.workflow import NOISE_WARNING_SCALE

pytestmark = pytest.mark.realdata


def _odd_even(stack, z):
    """Calibrate on the odd planes; localize the even ones, which the calibration never saw.
    Returns the calibration, the score of the even planes within ±500 nm against the piezo z
    (:func:`realdata.score_z`), their errors about its offset and their reported z_err_nm."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cal = lz.calibrate(stack[1::2], z[1::2], camera=lz.Camera(**FIT3D_CAMERA))
    said = [str(w.message) for w in record if issubclass(w.category, LatentzWarning)]
    noise = [m for m in said if "scatter in z" in m and "as much as gain 0.1" in m]
    assert len(noise) == int(cal.noise_scale < NOISE_WARNING_SCALE)
    locs = lz.localize(stack[0::2], calibration=cal)
    piezo = z[0::2][locs["frame"].to_numpy()]
    near = (np.abs(piezo) <= 500) & locs["in_range"].to_numpy()
    assert near.sum() >= 0.9 * np.count_nonzero(np.abs(z[0::2]) <= 500)
    score = score_z(locs["z_nm"].to_numpy()[near], piezo[near])
    error = locs["z_nm"].to_numpy()[near] - piezo[near] - score["offset"]
    return cal, score, error, locs["z_err_nm"].to_numpy()[near]


CROP = (slice(3, 18), slice(3, 18))


@pytest.mark.parametrize("crop", [None, CROP], ids=["21px", "15px"])
def test_fit3d_bead_odd_planes_calibrate_even_planes_localize(crop):
    """Truth: the piezo z of the even planes (fit3Dcspline's file, 10 nm steps), less one
    offset: the bead's focus, where latentz puts z = 0."""
    stack, z = fit3d_bead()
    if crop is not None:
        stack = stack[:, crop[0], crop[1]]
    cal, score, error, z_err = _odd_even(stack, z)
    print(score)
    assert cal.shape == "auto"  # astigmatism along the camera axes: ρ stays near 0
    # errors within 2x the measured plane-to-plane precision (measured: 3.9 / 3.3 nm, 3.1 /
    # 3.2 nm cropped); the z scale within 4 standard errors (~0.002 each) of 1
    assert score["rms"] <= 2 * score["jitter"], score
    assert abs(score["slope"] - 1) <= 4 * score["slope_se"], score
    coverage = np.mean(np.abs(error) <= z_err)
    # ~50 planes: a 68 % coverage has a sampling error of ±6.5 %, so 51–85 % (2.58 of them);
    # measured 69 % (21 px) and 76 % (15 px)
    assert 0.51 <= coverage <= 0.85, coverage


@pytest.mark.slow
def test_smlm_beads_calibrate_with_defaults():
    stack, z = smlm_beads()
    cal = lz.calibrate(stack, z, camera=lz.Camera(**SMLM_CAMERA))
    assert len(cal.kept) == 6
    assert cal.shape == "auto" and "auto" in cal.shape_choice["reason"]
    # the ROI is the recorded choice, and no candidate beats it near focus over the
    # particles both keep
    choice = cal.options["roi_choice"]
    assert cal.roi_size == choice["chosen"]
    assert choice["candidates"][str(cal.roi_size)]["beaten_by"]["core"] == []
    # the usable range stops before the ring images below focus (−600..−400 nm)
    assert np.all(cal.usable_z_nm[cal.kept, 0] > -400)


def test_fit3d_crop_bounds_the_roi_by_the_images():
    # a 15 px crop allows ROIs up to 13 px (a spot's centre needs a pixel of margin): every
    # candidate stays within that, and the choice is recorded with its reason
    stack, z = fit3d_bead()
    cal = lz.calibrate(stack[1::2, CROP[0], CROP[1]], z[1::2], camera=lz.Camera(**FIT3D_CAMERA))
    choice = cal.options["roi_choice"]
    assert cal.roi_size == choice["chosen"] <= 13
    assert all(int(r) <= 13 for r in choice["candidates"])
    assert f"roi_size={cal.roi_size}" in cal.options["roi_size_reason"]


@pytest.mark.slow
def test_shape_choice_is_robust_to_emitters_dimmer_than_the_beads():
    """auto_A has the better Cramér–Rao bound on the beads, but divides by A / A_ref: beads 1-5
    calibrate, bead 0's images at half their amplitude play an emitter of unknown brightness."""
    from latentz.calibration.traces import traces_table
    from latentz.calibration.workflow import calibrate_traces

    stack, z = smlm_beads()
    camera = lz.Camera(**SMLM_CAMERA)
    cal = lz.calibrate(stack, z, camera=camera)
    scores = cal.shape_choice["scores"]
    assert scores["auto_A"]["crlb_nm"] < scores["auto"]["crlb_nm"]  # better for bright beads
    assert cal.shape == "auto"  # ... but not for emitters of unknown brightness
    others = cal.traces.subset(np.arange(1, 6))
    dim = traces_table(cal.traces.subset([0])).assign(particle=0)
    dim["amplitude"] *= 0.5
    rms = {}
    for shape in ("auto", "auto_A"):
        model = calibrate_traces(others, camera=camera, shape=shape, roi_size=cal.roi_size)
        out = model.apply(dim)
        true_z = dim["z_nm"] - model.plane(*(cal.positions[0] * 100))
        near = (np.abs(true_z) <= 300).to_numpy()
        error = (out["z_nm"] - true_z).to_numpy()[near]
        rms[shape] = np.sqrt(np.nanmean(error**2)) if np.isfinite(error).any() else np.inf
        rms[shape + "_in_range"] = np.isfinite(error).mean()
    assert rms["auto"] < 30 and rms["auto_in_range"] > 0.95
    assert rms["auto_A"] > 3 * rms["auto"] or rms["auto_A_in_range"] < 0.5, rms


def test_three_of_the_smlm_beads_calibrate_without_numpy_warnings():
    """Beads 3-5 blanked to the background (a held-out set): what remains calibrates saying only
    what concerns the user, not numpy's all-NaN or divide-by-zero notes from inside."""
    stack, z = smlm_beads()
    truth = pd.read_csv(need("smlm2016-as-beads.csv"))
    background = np.median(stack, axis=(1, 2))
    for bead in (3, 4, 5):
        row = truth[(truth["bead"] == bead) & (truth["plane"] == 0)].iloc[0]
        cx, cy = round(row["x_nm"] / 100), round(row["y_nm"] / 100)  # 100 nm pixels
        stack[:, max(cy - 14, 0) : cy + 15, max(cx - 14, 0) : cx + 15] = background[:, None, None]
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cal = lz.calibrate(stack, z, camera=lz.Camera(**SMLM_CAMERA))
    assert len(cal.kept) == 3
    numpy_notes = [str(w.message) for w in record if w.category is RuntimeWarning
                   and "device=" not in str(w.message)]  # fmt: skip
    assert numpy_notes == []

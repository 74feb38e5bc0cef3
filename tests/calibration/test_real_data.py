"""Calibration on bead stacks from ../shared/data: the SMLM 2016 challenge's AS bead stack (made
by the challenge's simulator) and the fit3Dcspline bead (recorded). Marked ``realdata``: run
them alone with ``pytest -m realdata``; they skip, naming the missing file, without the folder.

Both stacks have astigmatism along the camera axes (ρ ≈ 0), so they exercise ``shape="auto"``.
Truth comes from outside latentz: the challenge's CSV (x, y, z of every bead at every plane) and
the fit3Dcspline piezo (10 nm steps). latentz puts z = 0 at the calibration beads' focus and x,
y at their apparent position in focus, so one constant per axis separates its axes from the
truth's; :func:`realdata.score_z` removes it and scores what is left.
"""

import numpy as np
import pandas as pd
import pytest
from realdata import FIT3D_CAMERA, fit3d_bead, need, score_z, smlm_beads

from latentz.calibration.traces import extract_traces, traces_table
from latentz.calibration.workflow import calibrate, calibrate_traces
from latentz.camera import Camera

pytestmark = pytest.mark.realdata


def test_smlm2016_held_out_beads_against_the_challenge_truth():
    """Beads 0-2 calibrate; beads 3-5, never seen, are localized at every plane within ±600 nm
    and scored against the challenge CSV's x, y, z for them."""
    stack, _ = smlm_beads()
    truth = pd.read_csv(need("smlm2016-as-beads.csv")).sort_values(["bead", "plane"])
    z = np.sort(truth["z_nm"].unique())
    focus = truth[truth["plane"] == np.argmin(np.abs(z))]
    # truth x, y are nm from the image corner; pixel [i, j] is centred at x = j, y = i
    beads = np.stack([focus["x_nm"] / 100 - 0.5, focus["y_nm"] / 100 - 0.5], axis=1)
    # 100 nm pixels, ~100 ADU baseline; gain: ~1.9e5 ADU in focus for 30,000 photons
    camera = Camera(offset=100.0, gain=0.16, readnoise=1.0, pixel_size_nm=100.0)
    # the beads are ~10 px wide at ±750 nm: a 31 px ROI holds them
    cal = calibrate(stack, z, camera=camera, shape="auto", field_model="nearest",
                    positions=[beads[:3]], roi_size=31)  # fmt: skip
    assert abs(cal.local.theta) < 0.1  # a cylindrical lens along the camera axes
    test = extract_traces([stack], z, camera=camera, positions=[beads[3:]], roi_size=31)
    out = cal.apply(traces_table(test))  # beads 3, 4, 5, each through all planes in order
    held_out = truth[truth["bead"] >= 3]
    near = (np.abs(held_out["z_nm"]) <= 600).to_numpy()
    assert out["in_range"].to_numpy()[near].mean() >= 0.95
    ok = near & out["in_range"].to_numpy()
    bead = held_out["bead"].to_numpy()[ok]
    for axis, shift in (("z", 0.0), ("x", 50.0), ("y", 50.0)):  # x, y: to pixel centres
        true = held_out[f"{axis}_nm"].to_numpy()[ok] - shift
        found = out[f"{axis}_nm"].to_numpy()[ok]
        reported = np.sqrt(np.mean(out[f"{axis}_err_nm"].to_numpy()[ok] ** 2))
        score = score_z(found, true, bead)
        each = [np.mean((found - true)[bead == b]) for b in (3, 4, 5)]
        print(f"smlm2016 {axis}: {score}, per-bead offsets {np.round(each, 1)}, RMS of the "
              f"reported errors {reported:.1f} nm")  # fmt: skip
        # errors about the common offset within 2x the RMS of the reported errors (measured:
        # z 18 / 15, x 4.3 / 4.5, y 5.2 / 5.8 nm); the offset is common to the three beads,
        # within 3 standard errors of a bead's mean (~120 planes each)
        assert score["rms"] <= 2 * reported, score
        assert np.ptp(each) <= 2 * 3 * score["rms"] / np.sqrt(score["n"] / 3), each
        if axis == "z":  # the z scale: slope 1 within 4 standard errors (~0.003 each)
            assert abs(score["slope"] - 1) <= 4 * score["slope_se"], score


def test_fit3dcspline_bead_against_its_piezo():
    """The bead's odd planes calibrate; its even planes, never seen, are localized within
    ±500 nm of focus and scored against the piezo z (10 nm steps, fit3Dcspline's file)."""
    stack, z = fit3d_bead()
    camera = Camera(**FIT3D_CAMERA)
    traces = extract_traces([stack], z, camera=camera, roi_size=17)
    assert len(traces) == 1
    cal = calibrate_traces(
        traces.planes(slice(1, None, 2)),
        camera=camera,
        shape="auto",
        field_model="nearest",
        tilt=False,  # one bead: no tilt plane to fit
    )
    even = traces.planes(slice(0, None, 2))
    out = cal.apply(traces_table(even))
    piezo = even.z_nm
    near = np.abs(piezo) <= 500
    assert out["in_range"].to_numpy()[near].all()
    score = score_z(out["z_nm"].to_numpy()[near], piezo[near])
    sigma = cal.particles["sigma_z"].iloc[0]
    print(f"fit3Dcspline: {score}; σ_z {sigma:.1f} nm")
    # errors about the offset within 2x the measured plane-to-plane precision; the z scale
    # within 4 standard errors of 1 (a 2 % scale error is ~10)
    assert score["rms"] <= 2 * score["jitter"], score
    assert abs(score["slope"] - 1) <= 4 * score["slope_se"], score
    # the offset is the bead's focus in piezo z, which the calibration reports (z_f)
    z_f = cal.particles["z_f"].iloc[0]
    assert abs(score["offset"] + z_f) <= 3 * score["rms"] / np.sqrt(score["n"]), (score, z_f)

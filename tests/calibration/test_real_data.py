"""Calibration on bead stacks from ../shared/data: the SMLM 2016 challenge's AS bead stack (made
by the challenge's simulator) and the fit3Dcspline bead (recorded). Marked ``realdata``: run
them alone with ``pytest -m realdata``; they skip, naming the missing file, without the folder.

Both stacks have astigmatism along the camera axes (ρ ≈ 0), so they exercise ``shape="auto"``.
The localizations are compared with the truth on the calibration's z axis: z = 0 is the focus of
the calibration bead(s) (the peak of A(z), after tilt removal), so the true z of a plane is its
piezo z minus the calibration's plane of best focus at the bead — an offset the calibration
determines from the calibration beads alone.
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from latentz.calibration.traces import extract_traces, traces_table
from latentz.calibration.workflow import calibrate, calibrate_traces
from latentz.camera import Camera

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"

pytestmark = pytest.mark.realdata


def _need(name):
    path = DATA / name
    if not path.exists():
        pytest.skip(f"real data {name} not found in {DATA} (shared data folder absent)")
    return path


def test_smlm2016_beads_auto_shape():
    tifffile = pytest.importorskip("tifffile")
    stack = tifffile.imread(_need("smlm2016-as-beads.tif"))
    truth = pd.read_csv(_need("smlm2016-as-beads.csv"))
    z = np.sort(truth["z_nm"].unique())
    focus = truth[truth["plane"] == np.argmin(np.abs(z))].sort_values("bead")
    # truth x, y are nm from the image corner; pixel [i, j] is centred at x = j, y = i
    beads = np.stack([focus["x_nm"] / 100 - 0.5, focus["y_nm"] / 100 - 0.5], axis=1)
    # 100 nm pixels, ~100 ADU baseline; gain: ~1.9e5 ADU in focus for 30,000 photons
    camera = Camera(offset=100.0, gain=0.16, readnoise=1.0, pixel_size_nm=100.0)
    # the beads are ~10 px wide at ±750 nm: a 31 px ROI holds them
    cal = calibrate(
        stack,
        z,
        camera=camera,
        shape="auto",
        field_model="nearest",
        positions=[beads[:3]],
        roi_size=31,
    )
    assert abs(cal.local.theta) < 0.1  # a cylindrical lens along the camera axes
    test = extract_traces([stack], z, camera=camera, positions=[beads[3:]], roi_size=31)
    out = cal.apply(traces_table(test))
    z_true = np.tile(z, 3) - cal.plane(out["x"] * 100, out["y"] * 100)
    near = np.abs(np.tile(z, 3)) <= 600
    err = (out["z_nm"] - z_true)[near]
    rmse = np.sqrt(np.nanmean(err**2))
    print(
        f"smlm2016: z RMSE {rmse:.1f} nm over ±600 nm, {out['in_range'][near].mean():.1%} in "
        f"range, focus offset of the calibration {cal.plane.c0:.0f} nm"
    )
    assert out["in_range"][near].mean() >= 0.95
    assert rmse <= 25.0


def test_fit3dcspline_bead_odd_even_planes():
    tifffile = pytest.importorskip("tifffile")
    stack = tifffile.imread(_need("fit3dcspline-bead.tif"))
    z = (np.arange(stack.shape[0]) - 100) * 10.0  # 10 nm steps, plane 100 near focus
    camera = Camera(offset=400.0, gain=0.1, readnoise=1.0, pixel_size_nm=100.0)
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
    z_true = even.z_nm - cal.plane(0.0, 0.0)  # one bead: the plane is flat at its focus
    near = np.abs(z_true) <= 500
    err = (out["z_nm"].to_numpy() - z_true)[near]
    rmse = np.sqrt(np.nanmean(err**2))
    sigma = cal.particles["sigma_z"].iloc[0]
    print(f"fit3Dcspline: z RMSE {rmse:.1f} nm within ±500 nm of focus; σ_z {sigma:.1f} nm")
    assert out["in_range"].to_numpy()[near].all()
    assert rmse <= 25.0

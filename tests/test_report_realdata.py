"""The report of a real-data calibration (the SMLM 2016 beads, ±750 nm) has no empty panel:
Fig. 3 uses the range the beads cover, and panels without data say so in words."""

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


@pytest.mark.realdata
@pytest.mark.slow
def test_smlm_beads_report_has_no_empty_panel(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    path = DATA / "smlm2016-as-beads.tif"
    if not path.exists():
        pytest.skip(f"real data {path.name} not found in {DATA} (shared data folder absent)")
    from latentz.calibration import calibrate
    from latentz.calibration.figures import figure2, figure3
    from latentz.camera import Camera
    from latentz.cli.steps import report_run

    camera = Camera(offset=100.0, gain=0.16, readnoise=1.0, pixel_size_nm=100.0)
    stack = tifffile.imread(path)
    cal = calibrate(
        stack, np.arange(-750.0, 751.0, 10.0), camera=camera, shape="auto", field_model="nearest"
    )
    fig3 = figure3(cal)
    titles = [ax.get_title() for ax in fig3.axes]
    assert "(c) n = 6" in titles, titles  # every bead has a mean σ_z over the covered range
    # every axis of Fig. 2 shows data or says in words why it cannot
    fig2 = figure2(cal, 0, shapes=("rho", "rho_A", "auto"))
    for ax in fig2.axes:
        if ax.axison and not ax.texts:
            assert ax.lines or ax.collections, ax.get_title()
    cal.save(tmp_path / "beads.h5")
    page = report_run(tmp_path, tmp_path / "report.html").read_text()
    assert "<title>latentz report: " in page and "Calibration quality: beads.h5" in page

"""`latentz demo --quick`: the whole job on built-in data writes a complete, self-contained report
and recovers the simulation's known pixel size and rotation."""

import base64
import io
import re

import pandas as pd
from browser import chromium, images_loaded
from PIL import Image

from latentz.demo import run_demo


def test_quick_demo_writes_report_and_recovers_truth(tmp_path):
    lines = run_demo(tmp_path, quick=True, progress=False)
    page = (tmp_path / "report.html").read_text()
    images = re.findall(r"src='data:image/png;base64,([^']+)'", page)
    assert len(images) >= 10  # PSFs, Figs. 2-3, focus, widefield, localization, motion figures
    for data in images:
        Image.open(io.BytesIO(base64.b64decode(data))).verify()
    if chromium() is not None:  # opened in a browser, with no network: every image shows
        assert images_loaded(tmp_path / "report.html", tmp_path) == (len(images), len(images))
    assert "Table 1" in page and "http://" not in page and "https://" not in page
    # the aperture array recovers the true 129.3 nm pixel within 0.05 %
    pixel = float(re.search(r"pixel size ([\d.]+)", lines[0]).group(1))
    assert abs(pixel / 129.3 - 1) < 5e-4
    # every degree of freedom is recovered within twice its Monte Carlo uncertainty (6 cycles:
    # the RMS of 6 unit normals exceeds 2 with probability ~0.05 %)
    within = pd.read_csv(tmp_path / "motion_vs_truth.csv").set_index("dof")
    assert len(within) == 6
    assert (within["rms_error"] < 2 * within["sigma"]).all(), within

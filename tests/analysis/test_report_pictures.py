"""The report's localization section shows the super-resolution image and the FRC, and the page
opens in a browser with every image."""

from __future__ import annotations

import re

import numpy as np
import pytest
from browser import chromium, images_loaded
from structures import rings

from latentz.report import sections, write_report


def test_localization_section_shows_the_image_and_the_resolution(tmp_path):
    rng = np.random.default_rng(5)
    locs, _ = rings(rng, n_rings=12, diameter_nm=250, precision_nm=8, per_ring=500, field_nm=5000)
    locs["in_range"] = True
    locs["good"] = True
    part = sections.localization_section(locs, name="rings")
    assert any(title.startswith("Super-resolution image") for title in part.figures)
    assert "Fourier ring correlation" in part.figures
    assert re.search(r"FRC resolution \d+\.\d nm", part.text)
    page = write_report([part], tmp_path / "report.html")
    if chromium() is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium)")
    assert images_loaded(page, tmp_path) == (3, 3)

import base64
import re

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from browser import chromium, images_loaded  # noqa: E402
from PIL import Image  # noqa: E402

from latentz._shared.figures import figure_png
from latentz.report import Section, write_report  # noqa: E402


def _figure():
    fig, ax = plt.subplots()
    ax.plot(np.arange(10), np.arange(10) ** 2)
    return fig


def test_report_embeds_every_figure_as_a_loadable_png(tmp_path):
    sections = [
        Section("Calibration", "z_f per particle.", figures={"Fig 2": figure_png(_figure())}),
        Section(
            "Motion",
            tables={"Table 1": pd.DataFrame({"dof": ["gamma"], "mean": [0.098]})},
            figures={"trajectory": figure_png(_figure()), "play": figure_png(_figure())},
        ),
    ]
    path = write_report(sections, tmp_path / "report.html", png_dir=tmp_path / "figs")
    page = path.read_text()
    sources = re.findall(r"src='([^']+)'", page)
    assert len(sources) == 3
    for src in sources:
        assert src.startswith("data:image/png;base64,")  # nothing to fetch
        png = base64.b64decode(src.split(",", 1)[1])
        with Image.open(__import__("io").BytesIO(png)) as image:
            image.verify()
    assert "http" not in page.replace("http-equiv", "")
    assert "<table" in page and "gamma" in page
    assert len(list((tmp_path / "figs").glob("*.png"))) == 3


def test_report_escapes_text(tmp_path):
    path = write_report([Section("<b>x</b>", "a < b")], tmp_path / "r.html")
    page = path.read_text()
    assert "&lt;b&gt;x&lt;/b&gt;" in page and "a &lt; b" in page


def test_report_opens_in_headless_chromium_with_every_image(tmp_path):
    if chromium() is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium)")
    sections = [
        Section("A", "x", figures={"one": figure_png(_figure()), "two": figure_png(_figure())}),
        Section("B", tables={"t": pd.DataFrame({"a": [1]})}, figures={"3": figure_png(_figure())}),
    ]
    path = write_report(sections, tmp_path / "report.html")
    assert images_loaded(path, tmp_path) == (3, 3)


def test_sections_of_one_name_get_distinct_anchors_and_figure_files(tmp_path):
    png = figure_png(_figure())
    sections = [Section("Calibration", figures={"Fig. 3: σ_z": png}) for _ in range(2)]
    page = write_report(sections, tmp_path / "r.html", png_dir=tmp_path / "figs").read_text()
    assert page.count("href='#calibration'") == 1 and page.count("href='#calibration-2'") == 1
    assert sorted(p.name for p in (tmp_path / "figs").glob("*.png")) == [
        "calibration-2-fig-3-z.png",
        "calibration-fig-3-z.png",
    ]


def test_a_table_column_has_one_number_format_and_a_dash_for_missing():
    from latentz.report import table_html

    page = table_html(pd.DataFrame({"x (µm)": [2020.0, 27.98], "drift": [np.nan, 0.5]}))
    # one format per column: both to the same decimals (three digits of the typical value)
    assert "<td>2020</td>" in page and "<td>28</td>" in page and "27.98" not in page
    assert "—" in page and "NaN" not in page

"""Fig. 2 and Fig. 3 of the local calibration are drawn and written atomically as PNG."""

import numpy as np
import pytest
from calib_synthetic import make_traces

from latentz.calibration.figures import figure2, figure3, figure_focus, interpercentile
from latentz.calibration.workflow import calibrate_traces
from latentz.camera import Camera


@pytest.fixture(scope="module")
def cal():
    traces, _ = make_traces(30, seed=30)
    return calibrate_traces(traces, camera=Camera(), field_model="nearest")


def test_figures_are_written(cal, tmp_path):
    fig2 = figure2(cal, 3, path=tmp_path / "fig2.png")
    fig3 = figure3(cal, path=tmp_path / "fig3.png", ranges_nm=[1000.0, 2000.0, 4000.0])
    figure_focus(cal, path=tmp_path / "focus.png")
    for name in ("fig2.png", "fig3.png", "focus.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*.part"))  # no temporary left behind
    assert fig2.axes[0].get_title().startswith("(a) particle 3 at (")
    # panel (a) needs no axis offset: positions are relative to the particle's focus
    fig2.canvas.draw()
    assert all(ax.xaxis.get_offset_text().get_text() == "" for ax in fig2.axes[:1])
    assert len(fig3.axes) >= 5


def test_fig3_uses_the_range_its_particles_cover(cal):
    """The particles span 6 µm (±3 µm): a mean σ_z over the default 6 µm would need every plane
    (an empty map on real stacks of ±0.75 µm); Fig. 3 uses 90 % of the span instead, so its
    map and histogram hold particles."""
    fig3 = figure3(cal)
    assert fig3.axes[1].get_title() == "(b) mean σ_z over 5.4 µm"
    (histogram,) = [ax.get_title() for ax in fig3.axes if ax.get_title().startswith("(c) n = ")]
    assert int(histogram.split("n = ")[1]) >= 20


def test_interpercentile_of_a_normal_sample():
    x = np.random.default_rng(31).normal(0, 2.0, 100000)
    # 16th–84th percentile of N(0, σ²) spans 2σ; the sampling error is ~0.5 %
    assert interpercentile(x) == pytest.approx(4.0, rel=0.02)


def test_bad_particle_index(cal):
    with pytest.raises(ValueError, match="particle"):
        figure2(cal, 30)

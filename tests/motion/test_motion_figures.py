"""Figures: every analysis renders to a PNG, written atomically."""

import numpy as np
import pytest
from matplotlib.figure import Figure

from latentz.motion import figures as F
from latentz.motion.rigid import rigid_motion
from latentz.motion.uncertainty import motion_uncertainty
from latentz.simulate.gear_motion import gear_trajectory


@pytest.fixture(scope="module")
def data():
    truth = gear_trajectory(200, seed=1, flexure_period_cycles=128, flexure_amplitude_nm=500.0)
    rng = np.random.default_rng(0)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0, 2.0, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0, 80.0, len(tracks))
    return tracks, rigid_motion(tracks)


def _figures(tracks, motion):
    return F.motion_figures(tracks, motion, motion_uncertainty(tracks, motion, n_sim=20))


def test_every_figure_renders_and_saves(data, tmp_path):
    figures = _figures(*data)
    assert set(figures) == {
        "motion",
        "residuals",
        "centroid",
        "play",
        "flexure",
        "monte_carlo",
        "out_of_plane",
    }
    expected_axes = {
        "motion": 12,
        "residuals": 6,
        "play": 2,
        "flexure": 4,
        "monte_carlo": 9,
        "out_of_plane": 1,
    }
    for name, fig in figures.items():
        assert isinstance(fig, Figure)
        if name in expected_axes:
            assert len(fig.axes) == expected_axes[name], name
        path = tmp_path / "sub" / f"{name}.png"
        F.save_figure(fig, path)
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == sorted(
        f"{n}.png" for n in figures
    )


def test_failed_save_leaves_no_file(data, tmp_path):
    fig = F.figure_residuals(data[1])
    with pytest.raises(ValueError, match="dpi"):
        F.save_figure(fig, tmp_path / "bad.png", dpi=-1)
    assert list(tmp_path.iterdir()) == []

"""Drift from a static segment and the Table-1 summary."""

import numpy as np
import pandas as pd
import pytest

from latentz.motion.rigid import rigid_motion
from latentz.motion.summary import drift, table1
from latentz.motion.uncertainty import motion_uncertainty
from latentz.simulate.gear_motion import gear_trajectory


def _static(n_frames=200, sigma_drift=(3.0, 1.5, 10.0), seed=0):
    """A motionless constellation displaced as a whole by random common-mode shifts."""
    rng = np.random.default_rng(seed)
    body = rng.uniform(-1e5, 1e5, (20, 3))
    shifts = rng.normal(0.0, sigma_drift, (n_frames, 3))
    pos = body[None] + shifts[:, None]
    tracks = pd.DataFrame(
        {
            "frame": np.repeat(np.arange(n_frames), 20),
            "particle": np.tile(np.arange(20), n_frames),
            "x_nm": pos[..., 0].ravel(),
            "y_nm": pos[..., 1].ravel(),
            "z_nm": pos[..., 2].ravel(),
        }
    )
    return tracks, shifts


def test_drift_is_the_rms_centroid_translation():
    tracks, shifts = _static()
    expected = np.sqrt(np.mean(np.diff(shifts, axis=0) ** 2, axis=0))
    got = drift(tracks)
    np.testing.assert_allclose(got.to_numpy(), expected, rtol=1e-9)
    assert got.attrs["n_pairs"] == 199
    # Missed detections do not bias it: the shift is common to every particle.
    gappy = tracks[np.random.default_rng(1).random(len(tracks)) > 0.1]
    np.testing.assert_allclose(drift(gappy).to_numpy(), expected, rtol=1e-9)
    segment = drift(tracks, frames=range(50, 101))
    np.testing.assert_allclose(
        segment.to_numpy(), np.sqrt(np.mean(np.diff(shifts[50:101], axis=0) ** 2, axis=0))
    )


def test_table1_combines_components():
    truth = gear_trajectory(60, seed=2)
    rng = np.random.default_rng(3)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0, 2.0, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0, 80.0, len(tracks))
    motion = rigid_motion(tracks)
    unc = motion_uncertainty(tracks, motion, n_sim=100)
    static, _ = _static()
    d = drift(static)
    table = table1(motion, unc, drift_nm=d)
    assert list(table.index) == ["gamma", "beta", "alpha", "dx_nm", "dy_nm", "dz_nm"]
    np.testing.assert_allclose(table["mean"], motion[table.index].mean())
    np.testing.assert_allclose(
        table["total_range"], motion[table.index].max() - motion[table.index].min()
    )
    np.testing.assert_allclose(table["localization"], unc["sigma"])
    assert table.loc[["gamma", "beta", "alpha"], "drift"].isna().all()
    np.testing.assert_allclose(table.loc[["dx_nm", "dy_nm", "dz_nm"], "drift"], d)
    np.testing.assert_allclose(
        table["total"] ** 2, unc["sigma"] ** 2 + np.nan_to_num(table["drift"]) ** 2
    )
    no_drift = table1(motion, unc)
    np.testing.assert_allclose(no_drift["total"], unc["sigma"])
    assert table.loc["gamma", "unit"] == "rad" and table.loc["dz_nm", "unit"] == "nm"


def test_bad_input_is_refused():
    tracks, _ = _static(n_frames=3)
    with pytest.raises(ValueError, match="at least 2 frames"):
        drift(tracks, frames=[0])
    disjoint = tracks[
        ((tracks.frame == 0) & (tracks.particle < 10))
        | ((tracks.frame == 1) & (tracks.particle >= 10))
    ]
    with pytest.raises(ValueError, match="shares a particle"):
        drift(disjoint)
    motion = rigid_motion(gear_trajectory(3).positions)
    with pytest.raises(ValueError, match="sigma"):
        table1(motion, pd.DataFrame({"std": [1.0]}))
    with pytest.raises(ValueError, match="lacks"):
        table1(motion, pd.DataFrame({"sigma": [1.0]}, index=["gamma"]))
    with pytest.raises(ValueError, match="gamma"):
        table1(motion.drop(columns="gamma"), pd.DataFrame({"sigma": [1.0]}))

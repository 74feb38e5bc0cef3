"""Analyses recover known inputs of the simulated gear."""

import numpy as np
import pandas as pd
import pytest

from latentz.motion.analyses import (
    centroid_trajectory,
    nominal_orientation,
    out_of_plane_play,
    peak_period,
    planar_residuals,
    play,
    residual_correlation,
    residual_spectrum,
)
from latentz.motion.rigid import rigid_motion
from latentz.simulate.gear_motion import gear_trajectory

N_CYCLES = 2000  # the paper's measurement length


def _noisy(truth, seed, lateral=2.0, axial=80.0):
    rng = np.random.default_rng(seed)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0.0, lateral, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0.0, axial, len(tracks))
    return tracks


@pytest.fixture(scope="module")
def flexing():
    truth = gear_trajectory(
        N_CYCLES, seed=6, flexure_period_cycles=128, flexure_amplitude_nm=2000.0
    )
    tracks = _noisy(truth, 2)
    return truth, tracks, rigid_motion(tracks)


def test_flexure_period_128_gives_the_fourier_peak_at_128(flexing):
    _, tracks, motion = flexing
    # A peak can be placed to within half a Rayleigh cell, P^2 / (2 T) = 4.1 cycles at P = 128.
    tol = 128**2 / (2 * N_CYCLES)
    rigid = residual_spectrum(motion["frame"].to_numpy(), motion["rms_z_nm"].to_numpy())
    assert peak_period(rigid) == pytest.approx(128, abs=tol)
    planar = planar_residuals(tracks)
    rms = np.sqrt((planar["res_z_nm"] ** 2).groupby(planar["frame"]).mean())
    spectrum = residual_spectrum(rms.index.to_numpy(), rms.to_numpy())
    assert peak_period(spectrum) == pytest.approx(128, abs=tol)


def test_flexure_correlates_planar_and_rigid_residuals(flexing):
    truth, tracks, _ = flexing
    with_flexure = residual_correlation(tracks)["correlation"].mean()
    plain = residual_correlation(_noisy(gear_trajectory(400, seed=6), 3))["correlation"]
    # Pure noise: the rigid residual n_i - R n_(i-1) and the planar residual n_i share n_i, so
    # r = 1/sqrt(2) less what the fits absorb (3 of 28 values each, ~10 %); 400 pairs give
    # +-0.04 per particle, +-0.01 for the mean of 28.
    assert plain.mean() == pytest.approx(1 / np.sqrt(2), abs=0.1)
    # Flexure dominates the planar residuals (the bend itself) but reaches the rigid residuals
    # only through its change between cycles: still positive, but weaker (the paper: 0.20).
    assert 0.0 < with_flexure < plain.mean()


def test_out_of_plane_play_slope_within_10_percent():
    truth = gear_trajectory(N_CYCLES, seed=5)
    tracks = _noisy(truth, 1)
    result = out_of_plane_play(tracks, rigid_motion(tracks))
    assert result.slope_rad == pytest.approx(truth.out_of_plane_play_rad, rel=0.10)
    assert result.slope_err_rad < 0.1 * result.slope_rad
    assert len(result.particles) == 28 and (result.particles["n_locations"] == 64).all()


def test_nominal_orientation_counts_steps():
    truth = gear_trajectory(300, seed=7)
    orient = nominal_orientation(rigid_motion(truth.positions))
    # The rotational play (5 mrad) is far below half a step (49 mrad).
    np.testing.assert_array_equal(orient["nominal"], np.arange(301) % 64)


def test_centroid_ignores_missed_detections():
    truth = gear_trajectory(50, seed=8)
    motion = rigid_motion(truth.positions)
    full = centroid_trajectory(truth.positions, motion)
    mean = truth.positions.groupby("frame")[["x_nm", "y_nm", "z_nm"]].mean()
    np.testing.assert_allclose(full[["x_nm", "y_nm", "z_nm"]], mean, atol=1e-6)
    rng = np.random.default_rng(0)
    gappy = truth.positions[rng.random(len(truth.positions)) > 0.2]
    partial = centroid_trajectory(gappy, motion)
    np.testing.assert_allclose(partial[["x_nm", "y_nm", "z_nm"]], mean, atol=1e-6)


def test_play_ranges_reflect_the_clearance():
    still = gear_trajectory(640, seed=9, play_nm=0.0, rotation_play_mrad=0.0, nutation_mrad=0.0)
    ranges = play(centroid_trajectory(still.positions, rigid_motion(still.positions)))
    assert len(ranges) == 64 and ranges["n_visits"].sum() == 641 and ranges["n_visits"].min() == 10
    assert ranges[["radial_range_nm", "tangential_range_nm", "axial_range_nm"]].max().max() < 1e-6
    loose = gear_trajectory(640, seed=9, play_nm=400.0, rotation_play_mrad=0.0, nutation_mrad=0.0)
    ranges = play(centroid_trajectory(loose.positions, rigid_motion(loose.positions)))
    # The hub wanders in a disc of 400 nm diameter: no range can exceed it, and 10 uniform
    # samples span most of it.
    assert ranges["radial_range_nm"].max() <= 400.0 + 1e-6
    assert ranges["radial_range_nm"].median() > 200.0
    assert ranges["axial_range_nm"].max() < 1e-6


def test_spectrum_of_a_sinusoid():
    frames = np.arange(1000)
    values = 3.0 * np.sin(2 * np.pi * frames / 50.0) + 7.0
    spectrum = residual_spectrum(frames, values)
    assert spectrum["amplitude"].max() == pytest.approx(3.0, rel=0.01)
    assert peak_period(spectrum) == pytest.approx(50.0, abs=0.05)
    gappy = residual_spectrum(frames[::3], values[::3])
    assert peak_period(gappy, min_period=10) == pytest.approx(50.0, abs=0.05)


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda: residual_spectrum(np.arange(5), np.arange(4)), ValueError, "equal length"),
        (lambda: residual_spectrum(np.arange(3), np.arange(3)), ValueError, "at least 4"),
        (
            lambda: residual_spectrum(np.arange(9), np.arange(9), oversample=0),
            ValueError,
            "oversample",
        ),
        (
            lambda: peak_period(residual_spectrum(np.arange(9), np.arange(9.0)), min_period=100),
            ValueError,
            "Fewer than 3",
        ),
        (lambda: nominal_orientation(pd.DataFrame({"gamma": [0.1]})), ValueError, "frame"),
        (lambda: play(pd.DataFrame({"x_nm": [0.0]})), ValueError, "nominal"),
        (
            lambda: planar_residuals(
                gear_trajectory(2, n_particles=3).positions.query("particle < 2")
            ),
            ValueError,
            "at least 3",
        ),
    ],
)
def test_bad_input_is_refused(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_out_of_plane_play_needs_revisits():
    truth = gear_trajectory(10, n_particles=6, seed=1)
    motion = rigid_motion(truth.positions)
    with pytest.raises(ValueError, match="revisit"):
        out_of_plane_play(truth.positions, motion)
    with pytest.raises(ValueError, match="min_visits"):
        out_of_plane_play(truth.positions, motion, min_visits=1)

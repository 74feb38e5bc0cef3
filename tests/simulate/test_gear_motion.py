"""Ground-truth gear kinematics: the positions obey the stated rigid motion exactly."""

import dataclasses

import numpy as np
import pytest

from latentz.simulate.gear_motion import gear_trajectory


def _stack(truth):
    pos = truth.positions.sort_values(["frame", "particle"])
    n = truth.body_nm.shape[0]
    return pos[["x_nm", "y_nm", "z_nm"]].to_numpy().reshape(-1, n, 3)


def test_positions_follow_the_true_motion_about_the_centre():
    truth = gear_trajectory(200, seed=3)
    p = _stack(truth) - truth.centre_nm
    predicted = np.einsum("kab,kjb->kja", truth.rotation, p[:-1]) + truth.delta_nm[:, None, :]
    np.testing.assert_allclose(predicted, p[1:], rtol=0, atol=1e-7)
    np.testing.assert_allclose(truth.centre_nm, _stack(truth).reshape(-1, 3).mean(0), atol=1e-9)


def test_motion_is_of_the_papers_order_of_magnitude():
    truth = gear_trajectory(640, seed=1)
    m = truth.motion
    # 64 steps per revolution: the mean step is 2π/64 up to the play's telescoping sum / n.
    assert m.gamma.mean() == pytest.approx(2 * np.pi / 64, abs=3 * 5e-3 * np.sqrt(2) / 640)
    # The in-plane clearance of 400 nm gives translations spanning about twice that.
    assert 500 < np.ptp(m.dx_nm) < 1000
    # Nutation close to the static tilt of 9 mrad.
    assert 5e-3 < m.beta.median() < 15e-3
    assert m.alpha_defined.all()


def test_particles_lie_on_the_gear_and_apart():
    truth = gear_trajectory(1, n_particles=28, gear_diameter_um=328.0, seed=2)
    r = np.hypot(truth.body_nm[:, 0], truth.body_nm[:, 1])
    assert r.min() >= 0.3 * 164e3 and r.max() <= 0.95 * 164e3
    d = np.hypot(*(truth.body_nm[:, None, :2] - truth.body_nm[None, :, :2]).transpose(2, 0, 1))
    assert d[~np.eye(28, dtype=bool)].min() >= 5000.0


def test_flexure_is_non_rigid_and_periodic():
    rigid = gear_trajectory(256, seed=4)
    bent = gear_trajectory(256, seed=4, flexure_period_cycles=128, flexure_amplitude_nm=300.0)
    dz = (_stack(bent) - _stack(rigid))[..., 2]
    # The bend m_k = (1 + sin(2πk/128))/2 vanishes at k = 96 and peaks at k = 32, 160.
    assert np.abs(dz[96]).max() < 1e-9
    assert 0 < dz[32].max() <= 300.0
    np.testing.assert_allclose(dz[32], dz[160], atol=1e-9 + 0.05 * 300)


def test_truth_is_immutable():
    truth = gear_trajectory(3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        truth.steps_per_rev = 3
    with pytest.raises(ValueError, match="read-only"):
        truth.rotation[0, 0, 0] = 1.0


def test_motion_about_another_centre_keeps_positions_consistent():
    truth = gear_trajectory(20, seed=5)
    c = np.array([1000.0, -2000.0, 50.0])
    m = truth.motion_about(c)
    p = _stack(truth) - c
    delta = m[["dx_nm", "dy_nm", "dz_nm"]].to_numpy()
    predicted = np.einsum("kab,kjb->kja", truth.rotation, p[:-1]) + delta[:, None, :]
    np.testing.assert_allclose(predicted, p[1:], atol=1e-7)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"n_cycles": 0}, ValueError, "n_cycles"),
        ({"n_cycles": 2.5}, TypeError, "n_cycles"),
        ({"n_cycles": 2, "gear_diameter_um": -1}, ValueError, "gear_diameter_um"),
        ({"n_cycles": 2, "play_nm": -1}, ValueError, "play_nm"),
        ({"n_cycles": 2, "flexure_amplitude_nm": 5.0}, ValueError, "flexure_period_cycles"),
        ({"n_cycles": 2, "n_particles": 500, "gear_diameter_um": 20.0}, ValueError, "n_particles"),
    ],
)
def test_bad_input_is_refused(kwargs, error, match):
    with pytest.raises(error, match=match):
        gear_trajectory(**kwargs)

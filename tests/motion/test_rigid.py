"""Rigid transforms: exact recovery, the eqs. 11-14 decomposition, ICP and bad input."""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from latentz.motion._axis_angle import decompose_rotation
from latentz.motion._kernels import kabsch_rotations_numba, kabsch_rotations_numpy
from latentz.motion.rigid import (
    RigidTransform,
    icp,
    icp_motion,
    kabsch,
    rigid_motion,
    rotation_from_angles,
)
from latentz.simulate.gear_motion import gear_trajectory

DOF = ["gamma", "beta", "alpha", "dx_nm", "dy_nm", "dz_nm"]
SCALE_NM = 1e5  # size of the constellations below


def _tracks(frames_xyz: np.ndarray) -> pd.DataFrame:
    n_frames, n = frames_xyz.shape[:2]
    return pd.DataFrame(
        {
            "frame": np.repeat(np.arange(n_frames), n),
            "particle": np.tile(np.arange(n), n_frames),
            "x_nm": frames_xyz[..., 0].ravel(),
            "y_nm": frames_xyz[..., 1].ravel(),
            "z_nm": frames_xyz[..., 2].ravel(),
        }
    )


def _series(rotations, translations, seed=0, n=28):
    """Positions under known transforms p_i = R_i p_{i-1} + t_i (raw coordinates)."""
    rng = np.random.default_rng(seed)
    p = [rng.uniform(-SCALE_NM, SCALE_NM, (n, 3)) * [1, 1, 0.05]]
    for r, t in zip(rotations, translations, strict=True):
        p.append(p[-1] @ r.T + t)
    return np.array(p)


def _truth(rotvecs, translations, positions):
    """γ, β, α of the rotation vectors that made the motion (angle |v|; axis v/|v| at nutation β
    from z, precession α about z) and Δ about the centre of rotation (mean of all positions)."""
    rotations = Rotation.from_rotvec(rotvecs).as_matrix()
    centre = positions.reshape(-1, 3).mean(0)
    delta = translations + np.einsum("nij,j->ni", rotations, centre) - centre
    gamma = np.linalg.norm(rotvecs, axis=1)
    horizontal = np.hypot(rotvecs[:, 0], rotvecs[:, 1])
    beta = np.arctan2(horizontal, rotvecs[:, 2])
    alpha = np.arctan2(rotvecs[:, 1], rotvecs[:, 0])
    return gamma, beta, alpha, horizontal > 0, delta


def test_numba_kernel_matches_numpy_svd_twin():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(500, 12, 3))
    rot = Rotation.random(500, random_state=1).as_matrix()
    dst = src @ np.swapaxes(rot, 1, 2) + rng.normal(scale=0.2, size=src.shape)
    a = src - src.mean(1, keepdims=True)
    h = np.einsum("nki,nkj->nij", a, dst - dst.mean(1, keepdims=True))
    h = np.concatenate([h, rng.normal(size=(500, 3, 3))])  # arbitrary, incl. reflections
    out = np.empty_like(h)
    kabsch_rotations_numba(h, out)
    np.testing.assert_allclose(out, kabsch_rotations_numpy(h), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=1e-12)


@pytest.mark.parametrize("gamma_scale", [1.0, 1e-5])
def test_random_motions_are_recovered_exactly(gamma_scale):
    rng = np.random.default_rng(7)
    rotvec = Rotation.random(40, random_state=3).as_rotvec() * gamma_scale
    rotations = Rotation.from_rotvec(rotvec).as_matrix()
    translations = rng.normal(scale=1e3, size=(40, 3))
    pos = _series(rotations, translations)
    motion = rigid_motion(_tracks(pos))
    gamma, beta, alpha, defined, delta = _truth(rotvec, translations, pos)
    assert defined.all() and motion.alpha_defined.all()
    np.testing.assert_allclose(motion.gamma, gamma, rtol=1e-9)
    np.testing.assert_allclose(motion.beta, beta, rtol=1e-9)
    np.testing.assert_allclose(motion.alpha, alpha, rtol=1e-9)
    got = motion[["dx_nm", "dy_nm", "dz_nm"]].to_numpy()
    np.testing.assert_allclose(got, delta, rtol=1e-9, atol=1e-9 * SCALE_NM)
    assert (motion.n_particles == 28).all()
    assert motion[["rms_x_nm", "rms_y_nm", "rms_z_nm"]].to_numpy().max() < 1e-9 * SCALE_NM


def test_vertical_axis_flags_alpha_as_ill_defined():
    angles = np.array([0.098, 0.2, 1e-4])
    rotations = Rotation.from_rotvec(np.outer(angles, [0, 0, 1])).as_matrix()
    pos = _series(rotations, np.zeros((3, 3)), seed=2)
    motion = rigid_motion(_tracks(pos))
    np.testing.assert_allclose(motion.gamma, angles, rtol=1e-9)
    assert (motion.beta < 1e-9).all()
    assert not motion.alpha_defined.any()
    assert motion.alpha.isna().all()


def test_decomposition_matches_eqs_11_to_14_and_inverts():
    rotvec = Rotation.random(100, random_state=5).as_rotvec()
    rot = Rotation.from_rotvec(rotvec).as_matrix()
    gamma, beta, alpha, _ = decompose_rotation(rot)
    # the angles of the rotation vectors that made the matrices (scipy, not latentz)
    true_gamma, true_beta, true_alpha, _, _ = _truth(rotvec, np.zeros((100, 3)), np.zeros((1, 3)))
    np.testing.assert_allclose(gamma, true_gamma, rtol=1e-9)
    np.testing.assert_allclose(beta, true_beta, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(alpha, true_alpha, rtol=1e-9)
    u = np.stack(
        [rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]], 1
    )
    norm = np.linalg.norm(u, axis=1)
    small = gamma < np.pi / 2  # eq. 12 with asin is single-valued there
    np.testing.assert_allclose(gamma[small], np.arcsin(norm / 2)[small], rtol=1e-9)
    np.testing.assert_allclose(beta, np.pi / 2 - np.arcsin(u[:, 2] / norm), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(alpha, np.arctan2(u[:, 1], u[:, 0]), rtol=1e-12)
    np.testing.assert_allclose(rotation_from_angles(gamma, beta, alpha), rot, atol=1e-12)


def test_rigid_transform_object_round_trips():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3))
    true = RigidTransform(Rotation.random(random_state=2).as_matrix(), np.array([1.0, -2, 3]))
    fit = RigidTransform.from_estimate(src, true.apply(src))
    np.testing.assert_allclose(fit.rotation, true.rotation, atol=1e-12)
    np.testing.assert_allclose(fit.residuals(src, true.apply(src)), 0, atol=1e-12)
    np.testing.assert_allclose(fit.inv().apply(fit.apply(src)), src, atol=1e-12)


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3))
    mirrored = src * [1, 1, -1]
    rot, _ = kabsch(src, mirrored)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)


def test_missing_particles_and_too_few_common_particles():
    truth = gear_trajectory(6, n_particles=8, seed=4)
    tracks = truth.positions
    drop = (tracks.frame == 2) & (tracks.particle < 3)
    drop |= (tracks.frame == 5) & (tracks.particle < 6)  # 2 particles left in frame 5
    motion = rigid_motion(tracks[~drop].reset_index(drop=True), centre_nm=truth.centre_nm)
    assert motion.n_particles.tolist() == [8, 5, 5, 8, 2, 2]
    ok = motion.n_particles >= 3
    assert motion.loc[~ok, DOF[:2] + DOF[3:]].isna().all().all()
    np.testing.assert_allclose(motion.loc[ok, DOF], truth.motion.loc[ok, DOF], rtol=1e-9, atol=1e-6)


def test_icp_without_correspondences_equals_the_linked_solution():
    truth = gear_trajectory(30, seed=6)
    rng = np.random.default_rng(8)
    tracks = truth.positions.copy()
    tracks[["x_nm", "y_nm"]] += rng.normal(0, 2.0, (len(tracks), 2))
    tracks["z_nm"] += rng.normal(0, 80.0, len(tracks))
    linked = rigid_motion(tracks)
    shuffled = tracks.sample(frac=1.0, random_state=1).drop(columns="particle")
    found = icp_motion(shuffled, max_distance_nm=20e3)
    assert found.converged.all() and (found.n_particles == 28).all()
    cols = DOF + ["rms_x_nm", "rms_y_nm", "rms_z_nm"]
    np.testing.assert_allclose(found[cols], linked[cols], rtol=1e-9, atol=1e-9)


def test_icp_recovers_a_permutation_and_reports_failure():
    rng = np.random.default_rng(9)
    src = rng.uniform(-1e5, 1e5, (25, 3))
    move = RigidTransform(Rotation.from_rotvec([0, 0, 0.05]).as_matrix(), np.array([300.0, 0, 0]))
    order = rng.permutation(25)
    result = icp(src, move.apply(src)[order], max_distance_nm=2e4)
    assert result
    np.testing.assert_array_equal(order[result.matches], np.arange(25))
    np.testing.assert_allclose(result.transform.rotation, move.rotation, atol=1e-12)
    far = icp(src, move.apply(src) + 1e6, max_distance_nm=10.0)
    assert not far


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda t: rigid_motion(t.drop(columns="z_nm")), ValueError, "z_nm"),
        (lambda t: rigid_motion(t[t.frame == 0]), ValueError, "at least 2 frames"),
        (lambda t: rigid_motion(pd.concat([t, t])), ValueError, "several rows"),
        (lambda t: rigid_motion(t, centre_nm=[1.0, 2.0]), ValueError, "centre_nm"),
        (lambda t: rigid_motion(t, axis_tol=-1.0), ValueError, "axis_tol"),
        (lambda t: rigid_motion(t.assign(x_nm=np.nan)), ValueError, "non-finite"),
        (lambda t: rigid_motion(t.iloc[:0]), ValueError, "at least one"),
        (lambda t: rigid_motion(np.zeros((3, 3))), TypeError, "DataFrame"),
        (lambda t: icp(np.zeros((2, 3)), np.zeros((5, 3))), ValueError, "source"),
        (lambda t: icp(np.zeros((5, 3)), np.zeros((5, 2))), ValueError, "target"),
        (lambda t: kabsch(np.zeros((5, 3)), np.zeros((4, 3))), ValueError, "equal shape"),
        (lambda t: icp_motion(t[t.frame == 0], max_distance_nm=1.0), ValueError, "2 frames"),
    ],
)
def test_bad_input_is_refused(call, error, match):
    tracks = gear_trajectory(3, n_particles=5).positions
    with pytest.raises(error, match=match):
        call(tracks)

"""rigid_motion and the Zernike basis under hostile input: exact recovery of a known rotation
(γ, β, α from its rotation vector) from any particle order, clear errors for empty, duplicate
and NaN tracks, and a bounded, finite Zernike design for any point in the field (Noll
normalisation: |Z| <= sqrt(2 (n + 1)))."""

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from latentz._shared.zernike import noll_to_nm, zernike_design
from latentz.motion import rigid_motion


def moving_tracks(seed, n_particles, n_frames):
    rng = np.random.default_rng(seed)
    points = rng.normal(0, 1000, (n_particles, 3))
    rotation = Rotation.from_rotvec(rng.normal(0, 0.05, 3))
    shift = rng.normal(0, 50, 3)
    rows, current = [], points
    for frame in range(n_frames):
        rows += [
            dict(frame=frame, particle=p, x_nm=c[0], y_nm=c[1], z_nm=c[2])
            for p, c in enumerate(current)
        ]
        current = rotation.apply(current) + shift
    return pd.DataFrame(rows), rotation


@given(
    seed=st.integers(0, 2**16),
    n_particles=st.integers(3, 12),
    n_frames=st.integers(2, 5),
    shuffle=st.booleans(),
)
def test_rigid_motion_recovers_known_rotation(seed, n_particles, n_frames, shuffle):
    tracks, rotation = moving_tracks(seed, n_particles, n_frames)
    if shuffle:
        tracks = tracks.sample(frac=1.0, random_state=seed)
    motion = rigid_motion(tracks)
    assert len(motion) == n_frames - 1
    # truth from the rotation vector that moved the particles: angle γ = |v|, its axis v/|v| at
    # nutation β from z and precession α about z. Noise-free 1000 nm points: round-off, 1e-9.
    v = rotation.as_rotvec()
    truth = {
        "gamma": np.linalg.norm(v),
        "beta": np.arctan2(np.hypot(v[0], v[1]), v[2]),
        "alpha": np.arctan2(v[1], v[0]),
    }
    for name, angle in truth.items():
        np.testing.assert_allclose(motion[name], angle, rtol=1e-9, atol=1e-12, err_msg=name)
    # Noise-free rigid data: residuals at round-off of 1000 nm coordinates.
    assert (motion[["rms_x_nm", "rms_y_nm", "rms_z_nm"]].to_numpy() < 1e-6).all()
    # The same rotation each step: identical angles and translation in every transition.
    angles = motion[["gamma", "beta", "dx_nm", "dy_nm", "dz_nm"]].to_numpy()
    assert np.allclose(angles, angles[0], rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda t: t.iloc[:0], "at least one localization"),
        (lambda t: t.drop(columns="z_nm"), "missing column"),
        (lambda t: pd.concat([t, t]), "several rows for one"),
        (lambda t: t.assign(x_nm=np.nan), "non-finite positions"),
        (lambda t: t.assign(y_nm=np.inf), "non-finite positions"),
        (lambda t: t[t["frame"] == 0], "at least 2 frames"),
    ],
)
def test_rigid_motion_bad_tracks(damage, match):
    tracks, _ = moving_tracks(1, 5, 3)
    with pytest.raises(ValueError, match=match):
        rigid_motion(damage(tracks))


@given(
    h=st.integers(1, 2048),
    w=st.integers(1, 2048),
    n_terms=st.integers(1, 120),
    fx=st.lists(st.floats(0, 1), min_size=1, max_size=20),
)
def test_zernike_design_finite_and_bounded(h, w, n_terms, fx):
    x = -0.5 + np.array(fx) * w
    y = -0.5 + np.array(fx[::-1]) * h
    design = zernike_design(x, y, field_shape=(h, w), n_terms=n_terms)
    n, m = noll_to_nm(n_terms)
    bound = np.sqrt(np.where(m == 0, 1.0, 2.0) * (n + 1))
    assert design.shape == (len(fx), n_terms)
    assert np.isfinite(design).all()
    assert (np.abs(design) <= bound * (1 + 1e-9)).all()


@pytest.mark.parametrize(
    ("x", "field_shape", "n_terms", "match"),
    [
        ([100.0], (20, 20), 10, "within the field"),
        ([-1.0], (20, 20), 10, "within the field"),
        ([1.0], (0, 20), 10, "field_shape"),
        ([1.0], (20, 20), 0, "n_terms"),
        ([[1.0]], (20, 20), 10, "x_px"),
    ],
)
def test_zernike_bad_input(x, field_shape, n_terms, match):
    with pytest.raises(ValueError, match=match):
        zernike_design(np.array(x), np.array(x), field_shape=field_shape, n_terms=n_terms)

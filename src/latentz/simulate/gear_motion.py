"""Ground-truth kinematics of a ratcheting microgear carrying fluorescent particles.

The model follows the load gear of the paper (Results, "Microsystem tracking"; Table 1; Figs. 6–8;
Supp. Figs. 18–20). Each motion cycle ends in one frame; frame 0 is the starting pose, so
``n_cycles`` cycles give ``n_cycles + 1`` frames and ``n_cycles`` transitions.

Pose of frame k (sample coordinates, nm; gear centre at the origin when there is no play)::

    p_jk = T(τ_k) Rz(θ_k) b_j + h_k + w_jk ẑ

- ``b_j``: particle j on the gear's top surface (z = 0), uniform in area at radii between
  0.3 and 0.95 of the gear radius, at least 5 µm apart.
- ``θ_k = 2π k / steps_per_rev + η_k``: ratcheting through ``steps_per_rev`` nominal orientations
  with rotational play in the plane, ``η_k ~ N(0, rotation_play_mrad)``.
- ``h_k``: translational play of the gear on its hub, uniform in a disc of diameter ``play_nm``
  (the clearance), independent per cycle, in the plane (z = 0).
- ``T(τ_k)``: a small tilt by the horizontal rotation vector
  ``τ_k = tilt_mrad·ê_s + (nutation_mrad / 2)·s(θ_k)·ê_p`` (+ optional ``rocking_mrad`` jitter).
  ``tilt_mrad`` is the static tilt of the gear with respect to the sensor (the paper's mean
  nutation, 9.1 mrad). ``s(θ) = clip(3 cos(θ/2), −1, 1)`` has a period of two revolutions: the
  gear rocks between two tilt states on odd and even revolutions, switching over about a fifth of
  a revolution (the reciprocating vertical shift of Supp. Fig. 19). ``nutation_mrad`` is the
  difference of the two states: the rotational play out of the plane, which is the slope of the
  maximum z range of each particle against its distance from the centre (Supp. Fig. 20; the
  paper measures 9.38 mrad).
- ``w_jk``: optional flexure, a non-rigid bend fixed in the laboratory frame (the gear is pinned
  near its coupling to the ring gear), ``w = A m_k (v / R)²`` with ``v`` the distance from the gear
  centre along the coupling direction ``ê_c``, ``R`` the gear radius, ``A =
  flexure_amplitude_nm`` and ``m_k = (1 + sin(2π k / P)) / 2``, ``P = flexure_period_cycles``.
  The paper sees it with a period of 128 cycles (two revolutions).

Defaults are of the paper's order of magnitude: γ ≈ 2π/64 = 98.2 mrad per cycle with a total range
of tens of mrad (Table 1: 56.7 mrad), Δx and Δy ranges of about 2 × ``play_nm`` (Table 1: ~780 nm),
mean β ≈ 9 mrad and an out-of-plane play of 9.4 mrad.

The true motion follows docs/conventions.md: positions centred on the centre of rotation (the
mean of all positions over all frames), ``p_i = R_i p_{i−1} + Δ_i``, and γ, β, α by eqs. 11–14.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from latentz._shared.validate import check_finite, check_int, check_positive

__all__ = ["GearTruth", "gear_trajectory"]

#: Direction (rad, from +x) of the horizontal axis of the static tilt.
STATIC_TILT_AXIS_RAD = 2.0
#: Direction (rad, from +x) of the horizontal axis about which the gear rocks (out-of-plane play).
PLAY_AXIS_RAD = 0.5
#: Direction (rad, from +x) of the coupling to the ring gear, along which the flexure bends.
COUPLING_RAD = 0.5
_MIN_SEPARATION_NM = 5000.0


@dataclass(frozen=True)
class GearTruth:
    """Immutable ground truth of a simulated gear movie.

    Attributes
    ----------
    positions : DataFrame
        frame, particle, x_nm, y_nm, z_nm for every particle in every frame.
    motion : DataFrame
        One row per transition (frame = the later frame): frame, gamma, beta, alpha (rad),
        alpha_defined, dx_nm, dy_nm, dz_nm, about ``centre_nm``.
    rotation : ndarray, shape (n_cycles, 3, 3)
        True ``R_i`` of each transition.
    delta_nm : ndarray, shape (n_cycles, 3)
        True ``Δ_i`` about ``centre_nm``.
    pose_rotation, pose_translation_nm : ndarray, shapes (n_frames, 3, 3), (n_frames, 3)
        Rigid pose of each frame: ``p = pose_rotation @ b + pose_translation_nm`` (before flexure).
    body_nm : ndarray, shape (n_particles, 3)
        Particle positions in the gear's own frame.
    centre_nm : ndarray, shape (3,)
        The centre of rotation: the mean of all positions over all frames.
    tilt_rad : ndarray, shape (n_frames, 2)
        The horizontal tilt vector τ_k.
    out_of_plane_play_rad : float
        The true rotational play out of the plane (``nutation_mrad`` in rad).
    steps_per_rev : int
    """

    positions: pd.DataFrame
    motion: pd.DataFrame
    rotation: np.ndarray
    delta_nm: np.ndarray
    pose_rotation: np.ndarray
    pose_translation_nm: np.ndarray
    body_nm: np.ndarray
    centre_nm: np.ndarray
    tilt_rad: np.ndarray
    out_of_plane_play_rad: float
    steps_per_rev: int

    def motion_about(self, centre_nm: np.ndarray) -> pd.DataFrame:
        """Return the true motion table with translations about another centre of rotation.

        ``Δ' = Δ + (R − I)(c' − c)``: the rotations are unchanged.
        """
        shift = np.asarray(centre_nm, dtype=float).reshape(3) - self.centre_nm
        delta = self.delta_nm + np.einsum("nij,j->ni", self.rotation, shift) - shift
        table = self.motion.copy()
        table[["dx_nm", "dy_nm", "dz_nm"]] = delta
        return table


def _place_particles(rng: np.random.Generator, n: int, radius_nm: float) -> np.ndarray:
    """Uniform in area in the annulus 0.3 R – 0.95 R, at least 5 µm apart (rejection sampling)."""
    # Disc packing bound: at most area / (√3/2 s²) points s apart fit in the annulus (+ its rim).
    area = np.pi * ((0.95 * radius_nm + _MIN_SEPARATION_NM / 2) ** 2 - (0.3 * radius_nm) ** 2)
    fits = n <= area / (np.sqrt(3) / 2 * _MIN_SEPARATION_NM**2)
    points: list[np.ndarray] = []
    for _ in range(200 * n if fits else 0):
        if len(points) == n:
            break
        r = radius_nm * np.sqrt(rng.uniform(0.3**2, 0.95**2))
        phi = rng.uniform(0.0, 2.0 * np.pi)
        p = np.array([r * np.cos(phi), r * np.sin(phi), 0.0])
        if all(np.hypot(*(p - q)[:2]) >= _MIN_SEPARATION_NM for q in points):
            points.append(p)
    if len(points) < n:
        raise ValueError(
            f"Cannot place `n_particles`={n} particles at least 5 µm apart on a gear of radius "
            f"{radius_nm / 1000:.1f} µm."
        )
    return np.array(points)


def _unit(angle: float) -> np.ndarray:
    return np.array([np.cos(angle), np.sin(angle)])


def _axis_angles(rotvec: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """γ, β, α (radians) and where α is defined, from rotation vectors (scipy's axis × angle):
    γ the angle, β the axis's angle from z, α its azimuth (undefined for a vertical axis)."""
    gamma = np.linalg.norm(rotvec, axis=-1)
    horizontal = np.hypot(rotvec[..., 0], rotvec[..., 1])
    beta = np.arctan2(horizontal, rotvec[..., 2])
    defined = horizontal > 1e-9
    alpha = np.where(defined, np.arctan2(rotvec[..., 1], rotvec[..., 0]), np.nan)
    return gamma, beta, alpha, defined


def _poses(
    rng: np.random.Generator,
    n_frames: int,
    steps_per_rev: int,
    rot_play: float,
    play: float,
    tilt: float,
    nutation: float,
    rocking: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gear's pose in each frame: rotation matrices (n_frames, 3, 3), hub offsets (nm)
    and tilt vectors (rad): a ratchet step with in-plane rotational play, the hub anywhere in
    a disc of diameter ``play``, the static tilt plus the nutation's two states (alternating
    with revolution parity) and random rocking."""
    k = np.arange(n_frames)
    theta = 2.0 * np.pi * k / steps_per_rev + rng.normal(0.0, rot_play, n_frames)
    hub_r = 0.5 * play * np.sqrt(rng.uniform(0.0, 1.0, n_frames))
    hub_phi = rng.uniform(0.0, 2.0 * np.pi, n_frames)
    hub = np.stack([hub_r * np.cos(hub_phi), hub_r * np.sin(hub_phi), np.zeros(n_frames)], 1)

    state = np.clip(3.0 * np.cos(0.5 * theta), -1.0, 1.0)
    tau = tilt * _unit(STATIC_TILT_AXIS_RAD) + 0.5 * nutation * state[:, None] * _unit(
        PLAY_AXIS_RAD
    )
    tau = tau + rng.normal(0.0, rocking, (n_frames, 2))
    tilt_rot = Rotation.from_rotvec(np.column_stack([tau, np.zeros(n_frames)]))
    spin = Rotation.from_rotvec(np.outer(theta, [0.0, 0.0, 1.0]))
    return (tilt_rot * spin).as_matrix(), hub, tau


def _motion_table(frames: np.ndarray, rot: np.ndarray, delta: np.ndarray) -> pd.DataFrame:
    """One row per transition into ``frames``: γ, β, α (rad) of its rotation matrix and its
    translation (nm) about the centre of rotation."""
    gamma, beta, alpha, defined = _axis_angles(Rotation.from_matrix(rot).as_rotvec())
    return pd.DataFrame(
        {
            "frame": frames,
            "gamma": gamma,
            "beta": beta,
            "alpha": alpha,
            "alpha_defined": defined,
            "dx_nm": delta[:, 0],
            "dy_nm": delta[:, 1],
            "dz_nm": delta[:, 2],
        }
    )


def gear_trajectory(
    n_cycles: int,
    *,
    n_particles: int = 28,
    gear_diameter_um: float = 328.0,
    steps_per_rev: int = 64,
    play_nm: float = 400.0,
    nutation_mrad: float = 9.4,
    flexure_period_cycles: float | None = None,
    flexure_amplitude_nm: float = 0.0,
    seed: int = 0,
    tilt_mrad: float = 9.0,
    rotation_play_mrad: float = 5.0,
    rocking_mrad: float = 0.0,
) -> GearTruth:
    """Simulate the true positions and motion of particles on a ratcheting gear.

    Parameters
    ----------
    n_cycles : int
        Number of motion cycles (transitions); the movie has ``n_cycles + 1`` frames.
    n_particles : int
        Number of particles on the gear (28 in the paper).
    gear_diameter_um : float
        Gear diameter in µm (328 µm in the paper).
    steps_per_rev : int
        Nominal orientations per revolution (64).
    play_nm : float
        In-plane translational clearance: the hub offset is uniform in a disc of this diameter.
    nutation_mrad : float
        Rotational play out of the plane: the difference between the two tilt states that
        alternate with revolution parity (mrad).
    flexure_period_cycles : float or None
        Period of the flexure in cycles; None for no flexure.
    flexure_amplitude_nm : float
        Peak flexure deflection at the rim along the coupling direction (nm).
    seed : int
        Seed of the random generator.
    tilt_mrad : float
        Static tilt of the gear with respect to the sensor (mrad).
    rotation_play_mrad : float
        Standard deviation of the in-plane rotational play η_k (mrad).
    rocking_mrad : float
        Standard deviation of a random per-cycle tilt jitter on each horizontal axis (mrad).

    Returns
    -------
    GearTruth
    """
    n_cycles = check_int("n_cycles", n_cycles, minimum=1)
    n_particles = check_int("n_particles", n_particles, minimum=3)
    steps_per_rev = check_int("steps_per_rev", steps_per_rev, minimum=2)
    radius = check_positive("gear_diameter_um", gear_diameter_um) * 500.0
    play = check_positive("play_nm", play_nm, allow_zero=True)
    nutation = check_finite("nutation_mrad", nutation_mrad) * 1e-3
    tilt = check_finite("tilt_mrad", tilt_mrad) * 1e-3
    rot_play = check_positive("rotation_play_mrad", rotation_play_mrad, allow_zero=True) * 1e-3
    rocking = check_positive("rocking_mrad", rocking_mrad, allow_zero=True) * 1e-3
    flex_amp = check_finite("flexure_amplitude_nm", flexure_amplitude_nm)
    if flexure_period_cycles is not None:
        flex_period = check_positive("flexure_period_cycles", flexure_period_cycles)
    elif flex_amp != 0.0:
        raise ValueError(
            f"`flexure_amplitude_nm`={flexure_amplitude_nm!r} needs `flexure_period_cycles`, "
            "got None."
        )
    rng = np.random.default_rng(seed)

    body = _place_particles(rng, n_particles, radius)
    n_frames = n_cycles + 1
    k = np.arange(n_frames)
    pose_r, hub, tau = _poses(rng, n_frames, steps_per_rev, rot_play, play, tilt, nutation,
                              rocking)  # fmt: skip
    pos = np.einsum("kab,jb->kja", pose_r, body) + hub[:, None, :]
    if flexure_period_cycles is not None:
        along = (pos[..., :2] - hub[:, None, :2]) @ _unit(COUPLING_RAD)
        m = 0.5 * (1.0 + np.sin(2.0 * np.pi * k / flex_period))
        pos[..., 2] += flex_amp * m[:, None] * (along / radius) ** 2

    centre = pos.reshape(-1, 3).mean(axis=0)
    rot = np.einsum("kab,kcb->kac", pose_r[1:], pose_r[:-1])
    raw_t = hub[1:] - np.einsum("kab,kb->ka", rot, hub[:-1])
    delta = raw_t + np.einsum("kab,b->ka", rot, centre) - centre
    positions = pd.DataFrame(
        {
            "frame": np.repeat(k, n_particles),
            "particle": np.tile(np.arange(n_particles), n_frames),
            "x_nm": pos[..., 0].ravel(),
            "y_nm": pos[..., 1].ravel(),
            "z_nm": pos[..., 2].ravel(),
        }
    )
    motion = _motion_table(k[1:], rot, delta)
    for array in (rot, delta, pose_r, hub, body, centre, tau):
        array.setflags(write=False)
    return GearTruth(
        positions=positions,
        motion=motion,
        rotation=rot,
        delta_nm=delta,
        pose_rotation=pose_r,
        pose_translation_nm=hub,
        body_nm=body,
        centre_nm=centre,
        tilt_rad=tau,
        out_of_plane_play_rad=float(nutation),
        steps_per_rev=steps_per_rev,
    )

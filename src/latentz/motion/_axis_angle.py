"""Axis–angle decomposition of rotation matrices by the paper's eqs. 11–14.

From a rotation matrix ``R`` the vector ``u = (r32 − r23, r13 − r31, r21 − r12)`` points along the
axis of rotation with ``|u| = 2 sin γ`` (eqs. 11–12). The nutation is the angle between the axis
and the extrinsic z axis, ``β = π/2 − asin(u3/|u|)`` (eq. 13), and the precession is the angle of
the axis about z, ``α = atan2(u2, u1)`` (eq. 14).

The formulas are evaluated in forms that are algebraically identical but accurate everywhere:
``γ = atan2(|u|, tr R − 1)`` (since ``tr R − 1 = 2 cos γ``) and ``β = atan2(hypot(u1, u2), u3)``,
which equal eqs. 12–13 where those are defined and keep full relative precision for near-identity
rotations and near-vertical axes, where ``asin`` loses digits.
"""

from __future__ import annotations

import numpy as np

__all__ = ["decompose_rotation", "axis_vector"]


def axis_vector(rotation: np.ndarray) -> np.ndarray:
    """Return ``u`` of eq. 11 for rotation matrices of shape (..., 3, 3), as shape (..., 3)."""
    r = np.asarray(rotation, dtype=float)
    return np.stack(
        [
            r[..., 2, 1] - r[..., 1, 2],
            r[..., 0, 2] - r[..., 2, 0],
            r[..., 1, 0] - r[..., 0, 1],
        ],
        axis=-1,
    )


def decompose_rotation(
    rotation: np.ndarray, *, axis_tol: float = 1e-9
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split rotation matrices into intrinsic rotation γ, nutation β and precession α (radians).

    Parameters
    ----------
    rotation : ndarray, shape (..., 3, 3)
        Proper rotation matrices.
    axis_tol : float
        α is flagged as ill-defined where the horizontal part of ``u``, ``hypot(u1, u2) =
        2 sin γ sin β``, is at most ``axis_tol`` (β ≈ 0 or γ ≈ 0, or γ ≈ π where ``u`` vanishes).
        β is then still returned but α is NaN.

    Returns
    -------
    gamma, beta, alpha : ndarray, shape (...)
        γ in [0, π], β in [0, π], α in (−π, π] (NaN where ill-defined).
    alpha_defined : ndarray of bool, shape (...)
    """
    r = np.asarray(rotation, dtype=float)
    u = axis_vector(r)
    norm = np.linalg.norm(u, axis=-1)
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    gamma = np.arctan2(norm, trace - 1.0)
    horizontal = np.hypot(u[..., 0], u[..., 1])
    beta = np.arctan2(horizontal, u[..., 2])
    defined = horizontal > axis_tol
    alpha = np.where(defined, np.arctan2(u[..., 1], u[..., 0]), np.nan)
    return gamma, beta, alpha, defined

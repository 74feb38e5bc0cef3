"""Rigid transformations between motion cycles: batched Kabsch, the motion table, and ICP.

The paper maps particle positions between consecutive cycles by rigid transformations (eqs. 7–9),
with positions centred on the centre of rotation, the mean of all positions over all frames, so that
``p_i = R_i p_{i−1} + Δ_i``. ``R_i`` is decomposed into γ, β, α by eqs. 11–14
(:mod:`latentz.motion._axis_angle`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from latentz._shared.validate import check_array, check_columns, check_int, check_positive
from latentz.motion._axis_angle import decompose_rotation
from latentz.motion._kernels import kabsch_rotations_numba, kabsch_rotations_numpy

__all__ = [
    "RigidTransform",
    "kabsch",
    "rigid_motion",
    "rigid_residuals",
    "rotation_from_angles",
    "icp",
    "IcpResult",
    "icp_motion",
    "resolve_by_icp",
    "tracks_to_array",
    "MOTION_COLUMNS",
]

POSITION_COLUMNS = ("x_nm", "y_nm", "z_nm")
DOF_COLUMNS = ("gamma", "beta", "alpha", "dx_nm", "dy_nm", "dz_nm")
MOTION_COLUMNS = (
    "frame",
    "previous_frame",
    *DOF_COLUMNS,
    "alpha_defined",
    "rms_x_nm",
    "rms_y_nm",
    "rms_z_nm",
    "n_particles",
)


def rotations_from_covariance(h: np.ndarray, *, engine: str = "numba") -> np.ndarray:
    """Least-squares rotations (n, 3, 3) from cross-covariances ``h`` (n, 3, 3).

    ``engine`` is "numba" (Horn's quaternion kernel) or "numpy" (batched SVD); both give the same
    proper rotations to machine precision.
    """
    h = np.ascontiguousarray(h, dtype=float).reshape(-1, 3, 3)
    if engine == "numpy":
        return kabsch_rotations_numpy(h)
    out = np.empty_like(h)
    kabsch_rotations_numba(h, out)
    return out


def kabsch(
    source: np.ndarray, target: np.ndarray, *, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transforms ``target ≈ R source + t``, batched.

    Parameters
    ----------
    source, target : ndarray, shape (..., n, 3)
        Corresponding points. Points with zero weight (or NaN in either array when ``weights`` is
        None) are ignored.
    weights : ndarray, shape (..., n), optional

    Returns
    -------
    rotation : ndarray, shape (..., 3, 3)
    translation : ndarray, shape (..., 3)
        NaN where fewer than three points carry weight.
    """
    src = np.asarray(source, dtype=float)
    dst = np.asarray(target, dtype=float)
    if src.shape != dst.shape or src.ndim < 2 or src.shape[-1] != 3:
        raise ValueError(
            f"Expected `source` and `target` of equal shape (..., n, 3), got {src.shape} and "
            f"{dst.shape}."
        )
    if weights is None:
        w = (np.isfinite(src).all(-1) & np.isfinite(dst).all(-1)).astype(float)
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=float), src.shape[:-1])
    src = np.where(w[..., None] > 0, src, 0.0)
    dst = np.where(w[..., None] > 0, dst, 0.0)
    total = w.sum(-1)
    safe = np.where(total > 0, total, 1.0)[..., None]
    a_bar = (w[..., None] * src).sum(-2) / safe
    b_bar = (w[..., None] * dst).sum(-2) / safe
    a = src - a_bar[..., None, :]
    b = dst - b_bar[..., None, :]
    h = np.matmul(np.swapaxes(a * w[..., None], -1, -2), b)
    rot = rotations_from_covariance(h).reshape(h.shape)
    trans = b_bar - np.einsum("...ij,...j->...i", rot, a_bar)
    bad = (w > 0).sum(-1) < 3
    rot[bad] = np.nan
    trans[bad] = np.nan
    return rot, trans


def rotation_from_angles(gamma, beta, alpha) -> np.ndarray:
    """Rotation matrices from γ, β, α (the inverse of eqs. 11–14); NaN α is taken as 0."""
    gamma, beta, alpha = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (gamma, beta, alpha))
    )
    alpha = np.nan_to_num(alpha)
    axis = np.stack(
        [np.sin(beta) * np.cos(alpha), np.sin(beta) * np.sin(alpha), np.cos(beta)], axis=-1
    )
    rotvec = (axis * gamma[..., None]).reshape(-1, 3)
    return Rotation.from_rotvec(rotvec).as_matrix().reshape(gamma.shape + (3, 3))


@dataclass(frozen=True)
class RigidTransform:
    """Immutable rigid transform(s) ``p ↦ R p + t``; batched over leading dimensions."""

    rotation: np.ndarray
    translation_nm: np.ndarray

    @classmethod
    def from_estimate(cls, source, target, *, weights=None) -> RigidTransform:
        """Least-squares fit of ``target ≈ R source + t`` (see :func:`kabsch`)."""
        rot, trans = kabsch(source, target, weights=weights)
        return cls(rot, trans)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points of shape (..., n, 3)."""
        p = np.asarray(points, dtype=float)
        return np.einsum("...ij,...kj->...ki", self.rotation, p) + self.translation_nm[..., None, :]

    def residuals(self, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``target − apply(source)``, shape (..., n, 3)."""
        return np.asarray(target, dtype=float) - self.apply(source)

    def inv(self) -> RigidTransform:
        """The inverse transform."""
        rt = np.swapaxes(self.rotation, -1, -2)
        return RigidTransform(rt, -np.einsum("...ij,...j->...i", rt, self.translation_nm))

    def angles(self, *, axis_tol: float = 1e-9):
        """γ, β, α (rad) and the α-defined flag by eqs. 11–14."""
        return decompose_rotation(self.rotation, axis_tol=axis_tol)


def tracks_to_array(tracks: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (frames, particles, positions) with positions (n_frames, n_particles, 3), NaN where
    a particle is not seen in a frame."""
    check_columns("tracks", tracks, ("frame", "particle", *POSITION_COLUMNS))
    if len(tracks) == 0:
        raise ValueError("Expected `tracks` to hold at least one localization, got 0 rows.")
    if tracks.duplicated(["frame", "particle"]).any():
        raise ValueError("`tracks` has several rows for one (frame, particle): link them first.")
    frames, fi = np.unique(tracks["frame"].to_numpy(), return_inverse=True)
    particles, pi = np.unique(tracks["particle"].to_numpy(), return_inverse=True)
    pos = np.full((frames.size, particles.size, 3), np.nan)
    values = tracks[list(POSITION_COLUMNS)].to_numpy(dtype=float)
    if not np.isfinite(values).all():
        raise ValueError("`tracks` has non-finite positions in x_nm, y_nm or z_nm.")
    pos[fi, pi] = values
    return frames, particles, pos


def _centre(tracks: pd.DataFrame, centre_nm) -> np.ndarray:
    if centre_nm is None:
        return tracks[list(POSITION_COLUMNS)].to_numpy(dtype=float).mean(axis=0)
    c = check_array("centre_nm", centre_nm, ndim=1)
    if c.shape != (3,):
        raise ValueError(f"Expected `centre_nm` to have shape (3,), got {c.shape}.")
    return c.astype(float)


def _fit_transitions(pos: np.ndarray):
    """Fit every consecutive pair of frames of ``pos`` (F, P, 3; centred, NaN = unseen)."""
    prev, curr = pos[:-1], pos[1:]
    both = np.isfinite(prev).all(-1) & np.isfinite(curr).all(-1)
    rot, trans = kabsch(prev, curr, weights=both)
    moved = np.einsum("tij,tkj->tki", rot, np.where(both[..., None], prev, 0.0))
    res = curr - moved - trans[:, None, :]
    res[~both] = np.nan
    return rot, trans, res, both


def rigid_residuals(tracks: pd.DataFrame, *, centre_nm=None) -> pd.DataFrame:
    """Residuals of the rigid transforms per particle and transition.

    Returns a table with frame (the later frame of each transition), particle, res_x_nm, res_y_nm,
    res_z_nm: ``p_i − (R_i p_{i−1} + Δ_i)`` for particles seen in both frames.
    """
    frames, particles, pos = tracks_to_array(tracks)
    c = _centre(tracks, centre_nm)
    _, _, res, both = _fit_transitions(pos - c)
    t_idx, p_idx = np.nonzero(both)
    return pd.DataFrame(
        {
            "frame": frames[1:][t_idx],
            "particle": particles[p_idx],
            "res_x_nm": res[t_idx, p_idx, 0],
            "res_y_nm": res[t_idx, p_idx, 1],
            "res_z_nm": res[t_idx, p_idx, 2],
        }
    )


def _motion_table(frames, rot, trans, rms, n, axis_tol, centre) -> pd.DataFrame:
    gamma, beta, alpha, defined = decompose_rotation(rot, axis_tol=axis_tol)
    table = pd.DataFrame(
        {
            "frame": frames[1:],
            "previous_frame": frames[:-1],
            "gamma": gamma,
            "beta": beta,
            "alpha": alpha,
            "dx_nm": trans[:, 0],
            "dy_nm": trans[:, 1],
            "dz_nm": trans[:, 2],
            "alpha_defined": defined,
            "rms_x_nm": rms[:, 0],
            "rms_y_nm": rms[:, 1],
            "rms_z_nm": rms[:, 2],
            "n_particles": n,
        }
    )
    table.attrs["centre_nm"] = centre.tolist()
    return table


def rigid_motion(tracks: pd.DataFrame, *, centre_nm=None, axis_tol: float = 1e-9) -> pd.DataFrame:
    """Rigid motion between consecutive frames of linked tracks, in six degrees of freedom.

    Parameters
    ----------
    tracks : DataFrame
        frame, particle, x_nm, y_nm, z_nm (one row per particle per frame; gaps allowed).
    centre_nm : array-like, shape (3,), optional
        Centre of rotation; by default the mean of all positions over all frames.
    axis_tol : float
        Threshold on ``hypot(u1, u2)`` below which α is ill-defined (see
        :func:`latentz.motion._axis_angle.decompose_rotation`).

    Returns
    -------
    DataFrame
        One row per transition between consecutive frames present in ``tracks``: frame (the later
        frame), previous_frame, gamma, beta, alpha (rad; α NaN where ill-defined), dx_nm, dy_nm,
        dz_nm (about the centre of rotation), alpha_defined, rms_x_nm, rms_y_nm, rms_z_nm (RMS
        residual over the particles seen in both frames) and n_particles. Transitions with fewer
        than three common particles have NaN motion. ``attrs["centre_nm"]`` holds the centre.
    """
    axis_tol = check_positive("axis_tol", axis_tol)
    frames, _, pos = tracks_to_array(tracks)
    if frames.size < 2:
        raise ValueError(f"Expected `tracks` to span at least 2 frames, got {frames.size}.")
    c = _centre(tracks, centre_nm)
    rot, trans, res, both = _fit_transitions(pos - c)
    n = both.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.nansum(res**2, axis=1) / n[:, None])
    return _motion_table(frames, rot, trans, rms, n, axis_tol, c)


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp`: the transform, ``matches[j]`` (index into target of source point
    j, −1 if unmatched), RMS distance of the matched pairs, iterations and convergence."""

    transform: RigidTransform
    matches: np.ndarray
    rms_nm: float
    iterations: int
    converged: bool

    def __bool__(self) -> bool:
        return self.converged


def icp(
    source: np.ndarray,
    target: np.ndarray,
    *,
    init: RigidTransform | None = None,
    max_distance_nm: float = np.inf,
    max_iter: int = 100,
) -> IcpResult:
    """Iterative closest point: rigid transform ``target ≈ R source + t`` without correspondences.

    Each iteration matches every transformed source point to its nearest target point (KD-tree),
    drops pairs farther than ``max_distance_nm`` and target points claimed by several sources, and
    refits by Kabsch. It stops when the matches no longer change.

    Parameters
    ----------
    source : ndarray, shape (n, 3)
    target : ndarray, shape (m, 3)
    init : RigidTransform, optional
        Starting transform (identity by default); for large motions pass a prediction.
    max_distance_nm : float
        Pairs farther apart than this are not matched.
    max_iter : int

    Returns
    -------
    IcpResult
        Falsy (``converged=False``) if the matches did not settle or fewer than 3 pairs remain.
    """
    src = check_array("source", source, ndim=2)
    dst = check_array("target", target, ndim=2)
    for name, arr in (("source", src), ("target", dst)):
        if arr.shape[1] != 3 or arr.shape[0] < 3:
            raise ValueError(f"Expected `{name}` to have shape (n >= 3, 3), got {arr.shape}.")
    max_distance_nm = check_positive("max_distance_nm", max_distance_nm)
    max_iter = check_int("max_iter", max_iter, minimum=1)
    tree = cKDTree(dst)
    transform = init if init is not None else RigidTransform(np.eye(3), np.zeros(3))
    matches = np.full(src.shape[0], -2)
    for iteration in range(1, max_iter + 1):
        dist, idx = tree.query(transform.apply(src), distance_upper_bound=max_distance_nm)
        idx = np.where(np.isfinite(dist), idx, -1)
        claimed = np.bincount(idx[idx >= 0], minlength=dst.shape[0])
        idx = np.where((idx >= 0) & (claimed[np.maximum(idx, 0)] == 1), idx, -1)
        if np.array_equal(idx, matches):
            ok = (idx >= 0).sum() >= 3
            res = dst[idx[idx >= 0]] - transform.apply(src[idx >= 0])
            rms = float(np.sqrt((res**2).sum(1).mean())) if ok else np.nan
            return IcpResult(transform, idx, rms, iteration, bool(ok))
        matches = idx
        keep = idx >= 0
        if keep.sum() < 3:
            break
        transform = RigidTransform.from_estimate(src[keep], dst[idx[keep]])
    return IcpResult(transform, matches, np.nan, max_iter, False)


def icp_motion(
    locs: pd.DataFrame,
    *,
    max_distance_nm: float,
    centre_nm=None,
    axis_tol: float = 1e-9,
    max_iter: int = 100,
) -> pd.DataFrame:
    """Rigid motion between consecutive frames of unlinked localizations by ICP.

    Each frame is registered to the previous one starting from the previous transition's transform
    (identity for the first), so rotations of the paper's size per cycle (≈ 98 mrad) are followed
    once the first is caught. Columns as :func:`rigid_motion`, plus ``converged``; n_particles
    counts the matched pairs and the RMS columns are over them.
    """
    check_columns("locs", locs, ("frame", *POSITION_COLUMNS))
    c = _centre(locs, centre_nm)
    groups = {f: g[list(POSITION_COLUMNS)].to_numpy(float) - c for f, g in locs.groupby("frame")}
    frames = np.array(sorted(groups))
    if frames.size < 2:
        raise ValueError(f"Expected `locs` to span at least 2 frames, got {frames.size}.")
    rot = np.full((frames.size - 1, 3, 3), np.nan)
    trans = np.full((frames.size - 1, 3), np.nan)
    rms = np.full((frames.size - 1, 3), np.nan)
    n = np.zeros(frames.size - 1, dtype=int)
    converged = np.zeros(frames.size - 1, dtype=bool)
    guess = None
    for t, (f0, f1) in enumerate(zip(frames[:-1], frames[1:], strict=True)):
        result = icp(
            groups[f0], groups[f1], init=guess, max_distance_nm=max_distance_nm, max_iter=max_iter
        )
        converged[t] = result.converged
        if not result:
            continue
        guess = result.transform
        keep = result.matches >= 0
        res = result.transform.residuals(groups[f0][keep], groups[f1][result.matches[keep]])
        rot[t], trans[t] = guess.rotation, guess.translation_nm
        rms[t] = np.sqrt((res**2).mean(0))
        n[t] = keep.sum()
    table = _motion_table(frames, rot, trans, rms, n, axis_tol, c)
    table["converged"] = converged
    return table


def _nearest_defined(rot: np.ndarray, t: int) -> RigidTransform:
    """The transform of the defined transition nearest to ``t`` (identity if none is)."""
    defined = np.flatnonzero(np.isfinite(rot).all(axis=(1, 2)))
    if defined.size == 0:
        return RigidTransform(np.eye(3), np.zeros(3))
    return RigidTransform(rot[defined[np.argmin(np.abs(defined - t))]], np.zeros(3))


def resolve_by_icp(
    motion: pd.DataFrame,
    locs: pd.DataFrame,
    *,
    max_distance_nm: float,
    unlinked_distance_nm: float | None = None,
    rms_factor: float = 3.0,
    axis_tol: float = 1e-9,
    max_iter: int = 100,
) -> pd.DataFrame:
    """Re-fit by ICP the transitions that linking left ambiguous.

    A transition is ambiguous where fewer particles were linked across it than were localized in
    both frames (a particle missed for longer than the linker's memory, a jump beyond its search
    range, a spurious spot), or where its RMS residual exceeds ``rms_factor`` times the median
    (a swap). ICP registers the two frames' localizations directly, starting from the linked
    transform or, where fewer than 3 particles were linked, from the rotation of the nearest
    linked transition; its result replaces the linked one when it converges and matches more
    particles, or as many with a smaller RMS residual.

    Parameters
    ----------
    motion : DataFrame
        :func:`rigid_motion` of the linked tracks (its ``attrs["centre_nm"]`` is used).
    locs : DataFrame
        The localizations that were linked: frame, x_nm, y_nm, z_nm.
    max_distance_nm : float
        Pairs farther apart than this are not matched, starting from a linked transform (the
        linker's search range).
    unlinked_distance_nm : float, optional
        The same, starting from the nearest linked rotation (default ``20 × max_distance_nm``,
        as the linker's first cycle).
    rms_factor : float
        A transition whose 3D RMS residual exceeds this times the median is re-fitted.

    Returns
    -------
    DataFrame
        ``motion`` with the ambiguous transitions re-fitted and a column ``method``: "kabsch"
        (linked tracks) or "icp".
    """
    check_columns("motion", motion, ("frame", "previous_frame", "n_particles"))
    check_columns("locs", locs, ("frame", *POSITION_COLUMNS))
    if "centre_nm" not in motion.attrs:
        raise ValueError("`motion` has no attrs['centre_nm']: pass the table of rigid_motion.")
    near = check_positive("max_distance_nm", max_distance_nm)
    far = check_positive(
        "unlinked_distance_nm", 20 * near if unlinked_distance_nm is None else unlinked_distance_nm
    )
    c = np.asarray(motion.attrs["centre_nm"], dtype=float)
    groups = {f: g[list(POSITION_COLUMNS)].to_numpy(float) - c for f, g in locs.groupby("frame")}
    frames = np.append(motion["previous_frame"].to_numpy(), motion["frame"].to_numpy()[-1:])
    angles = motion[["gamma", "beta", "alpha"]].to_numpy(float)
    rot = np.full((len(motion), 3, 3), np.nan)
    good = np.isfinite(angles[:, :2]).all(1)
    rot[good] = rotation_from_angles(*np.nan_to_num(angles[good]).T)
    trans = motion[["dx_nm", "dy_nm", "dz_nm"]].to_numpy(float).copy()
    rms = motion[["rms_x_nm", "rms_y_nm", "rms_z_nm"]].to_numpy(float).copy()
    n = motion["n_particles"].to_numpy().copy()
    method = np.full(len(motion), "kabsch", dtype=object)
    rms3d = np.sqrt((rms**2).sum(1))
    limit = check_positive("rms_factor", rms_factor) * np.nanmedian(rms3d)
    swapped = rms3d > limit
    empty = np.empty((0, 3))
    for t, (f0, f1) in enumerate(zip(frames[:-1], frames[1:], strict=True)):
        src, dst = groups.get(f0, empty), groups.get(f1, empty)
        if min(len(src), len(dst)) < 3 or (n[t] >= min(len(src), len(dst)) and not swapped[t]):
            continue
        if n[t] >= 3 and good[t]:
            init, reach = RigidTransform(rot[t], trans[t]), near
        else:  # rotate as the nearest linked cycle did, then match the centroids
            turn = _nearest_defined(rot, t).rotation
            init, reach = RigidTransform(turn, dst.mean(0) - turn @ src.mean(0)), far
        result = icp(src, dst, init=init, max_distance_nm=reach, max_iter=max_iter)
        keep = result.matches >= 0
        res = result.transform.residuals(src[keep], dst[result.matches[keep]])
        icp_rms = np.sqrt((res**2).sum(1).mean()) if keep.any() else np.inf
        # a fit no worse than the typical transition, with more pairs or a smaller residual
        better = icp_rms <= limit and (keep.sum() > n[t] or icp_rms < rms3d[t])
        if not result or not better:
            continue
        rot[t], trans[t] = result.transform.rotation, result.transform.translation_nm
        rms[t], n[t], method[t] = np.sqrt((res**2).mean(0)), keep.sum(), "icp"
    table = _motion_table(frames, rot, trans, rms, n, axis_tol, c)
    table["method"] = method
    return table

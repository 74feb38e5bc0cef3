"""Pixel size (magnification) and distortion from a regular array of sub-resolution apertures.

Paper Supp. Note 3: an aperture array of known pitch, localized in pixels,
calibrates the image pixel size in nanometres. The positions are modelled as a lattice,

    p_k = o + i_k a_1 + j_k a_2 + e_k,

with integer indices ``(i_k, j_k)`` found from the data, origin ``o`` and basis vectors
``a_1, a_2`` (pixels per pitch) fitted by linear least squares. The pixel size is the pitch over
the square root of the unit-cell area, ``pitch / sqrt(|det [a_1 a_2]|)``, and its uncertainty
comes from the least-squares covariance with the noise variance estimated from the residual
scatter, so it is honest for independent localization errors. What the lattice cannot describe
(distortion) can optionally be modelled by a Zernike field of the residual displacement.

The uncertainty is statistical. A field of apparent shifts whose linear part mimics a change of
magnification (for example from field-dependent aberrations of the aperture images) is absorbed
into the basis and does not show in the residuals; on the simulator's default aberrations this
amounts to about 7e-5 of the pixel size (tests/calibration/test_apertures.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from latentz._shared.validate import check_array, check_int, check_positive
from latentz.calibration.fieldmodels import FieldModel

__all__ = ["ApertureLattice"]


def _principal_vectors(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two shortest non-parallel lattice vectors, from the modes of neighbour directions."""
    k = min(9, len(points))
    dist, idx = cKDTree(points).query(points, k=k)
    step = float(np.median(dist[:, 1]))
    vec = (points[idx[:, 1:]] - points[:, None, :]).reshape(-1, 2)
    length = np.hypot(vec[:, 0], vec[:, 1])
    vec = vec[(length > 0.7 * step) & (length < 1.45 * step)]
    angle = np.mod(np.arctan2(vec[:, 1], vec[:, 0]), np.pi)
    found = []
    for _ in range(2):
        hist, edges = np.histogram(angle, bins=90, range=(0.0, np.pi))
        smooth = hist + np.roll(hist, 1) + np.roll(hist, -1)
        peak = (edges[np.argmax(smooth)] + np.pi / 180.0) % np.pi
        near = np.abs(np.angle(np.exp(2j * (angle - peak)))) / 2 < np.deg2rad(12)
        if not np.any(near):
            raise ValueError("Could not find two lattice directions in the aperture positions.")
        members = vec[near]
        members = members * np.sign(members @ [np.cos(peak), np.sin(peak)])[:, None]
        found.append(np.median(members, axis=0))
        far = np.abs(np.angle(np.exp(2j * (angle - peak)))) / 2 > np.deg2rad(30)
        vec, angle = vec[far], angle[far]
    a1, a2 = found
    # Canonical order and signs: a1 closest to +x, a2 closest to +y.
    if abs(a1[0]) / np.hypot(*a1) < abs(a2[0]) / np.hypot(*a2):
        a1, a2 = a2, a1
    return a1 * np.sign(a1[0] or 1.0), a2 * np.sign(a2[1] or 1.0)


def _lattice_lstsq(points: np.ndarray, ij: np.ndarray):
    """Origin and basis by least squares; returns params (3, 2), residuals, (D^T D)^-1."""
    design = np.column_stack([np.ones(len(ij)), ij])
    params = np.linalg.lstsq(design, points, rcond=None)[0]
    resid = points - design @ params
    return params, resid, np.linalg.inv(design.T @ design)


@dataclass(frozen=True, eq=False)
class ApertureLattice:
    """A regular lattice fitted to aperture positions.

    Attributes
    ----------
    pitch_nm : float
        Known array pitch, nm.
    origin_px : ndarray (2,)
        ``(x, y)`` of lattice index ``(0, 0)`` (the aperture nearest the centre), pixels.
    basis_px : ndarray (2, 2)
        Rows ``a_1`` (closest to +x) and ``a_2`` (closest to +y), pixels per pitch.
    covariance : ndarray (6, 6)
        Covariance of ``(o_x, a_1x, a_2x, o_y, a_1y, a_2y)``, pixels².
    indices : ndarray (n, 2) of int
        Lattice index ``(i, j)`` of each input position.
    used : ndarray (n,) of bool
        Positions kept by the fit (others were outliers or duplicates of a lattice site).
    sigma_px : float
        Residual scatter per coordinate of the used positions, pixels.
    positions_px : ndarray (n, 2)
        The measured ``(x, y)`` positions, pixels.
    distortion : FieldModel or None
        Zernike model of the residual displacement, columns ``(dx, dy)`` in pixels.

    Examples
    --------
    >>> i, j = (a.ravel() for a in np.meshgrid(np.arange(5), np.arange(5), indexing="ij"))
    >>> fit = ApertureLattice.from_estimate(10 + 40.0 * j, 12 + 40.0 * i, pitch_nm=5000.0)
    >>> round(fit.pixel_size_nm, 9)
    125.0
    >>> fit.predict(np.array([[-2, -2]])).round(9).tolist()  # indices count from the centre
    [[10.0, 12.0]]
    """

    pitch_nm: float
    origin_px: np.ndarray
    basis_px: np.ndarray
    covariance: np.ndarray
    indices: np.ndarray
    used: np.ndarray
    sigma_px: float
    positions_px: np.ndarray
    distortion: FieldModel | None = None

    @classmethod
    def from_estimate(
        cls,
        x_px: np.ndarray,
        y_px: np.ndarray,
        *,
        pitch_nm: float,
        clip: float = 5.0,
        distortion_terms: int = 0,
        field_shape: tuple[int, int] | None = None,
    ) -> ApertureLattice:
        """Fit a lattice to measured aperture positions.

        Parameters
        ----------
        x_px, y_px : ndarray (n,)
            Measured aperture positions, pixels (at least 4, not all on one line). Missing
            apertures are fine; spurious detections are rejected as outliers.
        pitch_nm : float
            Known pitch of the (square) array, nm.
        clip : float
            Positions whose residual exceeds ``clip`` robust standard deviations (from the median
            absolute deviation) are excluded, iteratively.
        distortion_terms : int
            If > 0, also fit a Zernike field of this many terms to the residual displacement
            (needs ``field_shape``).
        field_shape : (int, int), optional
            ``(H, W)`` of the field, pixels, for the distortion model.

        Returns
        -------
        ApertureLattice
        """
        x = check_array("x_px", x_px, ndim=1, dtype_kind="uif").astype(np.float64)
        y = check_array("y_px", y_px, ndim=1, dtype_kind="uif").astype(np.float64)
        if x.shape != y.shape:
            raise ValueError(f"Expected `y_px` to have shape {x.shape}, got {y.shape}.")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("Expected `x_px` and `y_px` to be finite.")
        if x.size < 4:
            raise ValueError(f"Expected at least 4 aperture positions, got {x.size}.")
        pitch = check_positive("pitch_nm", pitch_nm)
        clip = check_positive("clip", clip)
        distortion_terms = check_int("distortion_terms", distortion_terms, minimum=0)
        if distortion_terms and field_shape is None:
            raise ValueError("`field_shape` is required when `distortion_terms` > 0.")
        points = np.column_stack([x, y])
        a1, a2 = _principal_vectors(points)
        params = np.vstack(
            [points[np.argmin(np.hypot(*(points - np.median(points, 0)).T))], a1, a2]
        )
        # Index a growing disk about the central aperture, refitting as it grows, so that an
        # error in the initial basis never accumulates into a wrong integer index.
        dist = np.hypot(*(points - params[0]).T)
        radius = 2.5 * max(np.hypot(*a1), np.hypot(*a2))
        while True:
            sel = dist <= radius
            ij = np.rint((points[sel] - params[0]) @ np.linalg.inv(params[1:])).astype(int)
            if np.linalg.matrix_rank(np.column_stack([np.ones(len(ij)), ij])) == 3:
                params = _lattice_lstsq(points[sel], ij)[0]
            if np.all(sel):
                break
            radius *= 1.6
        used = np.ones(x.size, dtype=bool)
        for _ in range(10):
            ij = np.rint((points - params[0]) @ np.linalg.inv(params[1:])).astype(int)
            resid = points - np.column_stack([np.ones(len(ij)), ij]) @ params
            norm = np.hypot(*resid.T)
            scale = 1.4826 * np.median(np.abs(resid[used])) + 1e-12
            keep = norm <= clip * scale * np.sqrt(2.0)
            keep &= _first_per_site(ij, norm)
            design_ok = np.linalg.matrix_rank(np.column_stack([np.ones(keep.sum()), ij[keep]])) == 3
            if keep.sum() < 4 or not design_ok:
                raise ValueError("The aperture positions do not determine a 2-D lattice.")
            params, res_used, _ = _lattice_lstsq(points[keep], ij[keep])
            if np.array_equal(keep, used):
                break
            used = keep
        params, res_used, inv_normal = _lattice_lstsq(points[used], ij[used])
        dof = 2 * int(used.sum()) - 6
        if dof < 1:
            raise ValueError(f"Expected more than 3 usable apertures, got {int(used.sum())}.")
        sigma = float(np.sqrt(np.sum(res_used**2) / dof))
        cov = np.zeros((6, 6))
        cov[:3, :3] = cov[3:, 3:] = sigma**2 * inv_normal
        distortion = None
        if distortion_terms:
            distortion = FieldModel.from_estimate(
                x[used],
                y[used],
                res_used,
                kind="zernike",
                field_shape=field_shape,
                n_terms=distortion_terms,
            )
        return cls(pitch, params[0], params[1:], cov, ij, used, sigma, points, distortion)

    # ------------------------------------------------------------------ derived quantities
    @property
    def pixel_size_nm(self) -> float:
        """Mean pixel size in the sample plane, ``pitch / sqrt(unit-cell area in px²)``, nm."""
        return float(self.pitch_nm / np.sqrt(abs(np.linalg.det(self.basis_px))))

    @property
    def pixel_size_err_nm(self) -> float:
        """One-sigma uncertainty of :attr:`pixel_size_nm`, from the least-squares covariance, nm."""
        (a1x, a1y), (a2x, a2y) = self.basis_px
        det = a1x * a2y - a1y * a2x
        grad = np.array([0.0, a2y, -a1y, 0.0, -a2x, a1x]) * (-self.pixel_size_nm / (2.0 * det))
        return float(np.sqrt(grad @ self.covariance @ grad))

    @property
    def rotation_rad(self) -> float:
        """Angle of ``a_1`` from +x towards +y, radians."""
        return float(np.arctan2(self.basis_px[0, 1], self.basis_px[0, 0]))

    @property
    def anisotropy(self) -> float:
        """``|a_1| / |a_2| - 1``: zero for square pixels imaging a square array."""
        return float(np.hypot(*self.basis_px[0]) / np.hypot(*self.basis_px[1]) - 1.0)

    @property
    def shear_rad(self) -> float:
        """Angle between ``a_1`` and ``a_2`` minus pi/2, radians."""
        a1, a2 = self.basis_px
        return float(np.arctan2(a1[0] * a2[1] - a1[1] * a2[0], a1 @ a2) - np.pi / 2)

    def predict(self, indices: np.ndarray) -> np.ndarray:
        """Lattice positions ``(x, y)`` in pixels of integer indices ``(n, 2)``."""
        ij = check_array("indices", indices, ndim=2, dtype_kind="iu")
        if ij.shape[1] != 2:
            raise ValueError(f"Expected `indices` to have shape (n, 2), got {ij.shape}.")
        return self.origin_px + ij @ self.basis_px

    def residuals(self) -> np.ndarray:
        """Measured minus lattice position, ``(n, 2)`` pixels (all inputs, used or not)."""
        return self.positions_px - self.predict(self.indices)


def _first_per_site(ij: np.ndarray, norm: np.ndarray) -> np.ndarray:
    """Keep, at each lattice site, only the position closest to it."""
    order = np.lexsort((norm, ij[:, 1], ij[:, 0]))
    sorted_ij = ij[order]
    first = np.ones(len(ij), dtype=bool)
    first[1:] = np.any(sorted_ij[1:] != sorted_ij[:-1], axis=1)
    keep = np.zeros(len(ij), dtype=bool)
    keep[order[first]] = True
    return keep

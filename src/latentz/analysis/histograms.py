"""Localizations as images: the grid (a field of view in nm and its pixels), and histograms of the
positions blurred by each localization's own uncertainty or a fixed width.

These are the images that rendering shows, drift correction cross-correlates and FRC compares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import ndimage

from latentz._shared.validate import check_columns, check_positive

__all__ = ["Grid", "grid_for", "positions", "splat", "MAX_PIXELS"]

#: The largest side of an image, pixels: beyond it a render or FRC needs a larger pixel.
MAX_PIXELS = 8192

#: Blur widths are grouped on a log scale in steps of this ratio (each group is blurred at once).
_BLUR_STEP = 1.08


@dataclass(frozen=True)
class Grid:
    """A field of view ``[u0, u0 + n_u * pixel_nm) x [v0, v0 + n_v * pixel_nm)`` in nm, pixelated.

    ``u`` runs along image columns, ``v`` along rows (row 0 at ``v0``)."""

    u0: float
    v0: float
    pixel_nm: float
    n_u: int
    n_v: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_v, self.n_u)

    def pixel_of(self, u_nm: np.ndarray, v_nm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous pixel coordinates (column, row) of positions in nm; pixel centres are
        integers."""
        return (u_nm - self.u0) / self.pixel_nm - 0.5, (v_nm - self.v0) / self.pixel_nm - 0.5


def grid_for(
    u_nm: np.ndarray,
    v_nm: np.ndarray,
    pixel_nm: float,
    *,
    extent: tuple[float, float, float, float] | None = None,
    margin_nm: float = 0.0,
) -> Grid:
    """The grid covering the positions (or ``extent`` = (u_min, u_max, v_min, v_max) in nm) with
    ``margin_nm`` on every side; a clear error when it would exceed :data:`MAX_PIXELS`."""
    pixel_nm = check_positive("pixel_nm", pixel_nm)
    if extent is None:
        if len(u_nm) == 0:
            raise ValueError("No localizations with finite positions to make an image of.")
        extent = (np.min(u_nm), np.max(u_nm), np.min(v_nm), np.max(v_nm))
    u_min, u_max, v_min, v_max = (float(e) for e in extent)
    if not (u_max > u_min and v_max > v_min):
        raise ValueError(f"Expected an extent with max > min on both axes, got {extent}.")
    u0, v0 = u_min - margin_nm, v_min - margin_nm
    n_u = int(np.ceil((u_max + margin_nm - u0) / pixel_nm)) + 1
    n_v = int(np.ceil((v_max + margin_nm - v0) / pixel_nm)) + 1
    if max(n_u, n_v) > MAX_PIXELS:
        raise ValueError(
            f"An image of {n_u} x {n_v} pixels at {pixel_nm:g} nm is too large (at most "
            f"{MAX_PIXELS} a side): give a larger pixel_nm or a smaller extent."
        )
    return Grid(u0, v0, pixel_nm, n_u, n_v)


def positions(locs: pd.DataFrame, columns: tuple[str, ...]) -> pd.DataFrame:
    """The rows of ``locs`` whose ``columns`` are all finite, those columns only (as float)."""
    check_columns("locs", locs, columns)
    values = locs.loc[:, list(columns)].astype(np.float64)
    return values[np.isfinite(values.to_numpy()).all(axis=1)]


def _histogram(grid: Grid, u: np.ndarray, v: np.ndarray, weights: np.ndarray) -> np.ndarray:
    col, row = grid.pixel_of(u, v)
    col, row = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
    inside = (col >= 0) & (col < grid.n_u) & (row >= 0) & (row < grid.n_v)
    flat = np.bincount(
        row[inside] * grid.n_u + col[inside], weights=weights[inside], minlength=grid.n_u * grid.n_v
    )
    return flat.reshape(grid.shape)


def _blur_groups(sigma_nm: np.ndarray) -> np.ndarray:
    """Group index of each width on a log scale (widths within a factor 1.08 share a group)."""
    return np.round(np.log(np.maximum(sigma_nm, 1e-3)) / np.log(_BLUR_STEP)).astype(np.int64)


def splat(
    grid: Grid,
    u_nm: np.ndarray,
    v_nm: np.ndarray,
    *,
    sigma_u_nm: np.ndarray | float | None = None,
    sigma_v_nm: np.ndarray | float | None = None,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Image on ``grid`` of the positions, each a Gaussian of its own widths (nm) and weight.

    ``sigma_* = None`` bins the positions (a histogram). Widths are grouped within 8 % of each
    other and each group is binned then blurred once, so the cost grows with the number of
    distinct widths, not of localizations. Returns float64 of shape ``grid.shape``.
    """
    u, v = np.asarray(u_nm, dtype=np.float64), np.asarray(v_nm, dtype=np.float64)
    w = np.ones_like(u) if weights is None else np.asarray(weights, dtype=np.float64)
    if sigma_u_nm is None and sigma_v_nm is None:
        return _histogram(grid, u, v, w)
    su = np.broadcast_to(np.asarray(sigma_u_nm, dtype=np.float64), u.shape)
    sv = np.broadcast_to(np.asarray(sigma_v_nm, dtype=np.float64), u.shape)
    keys = np.stack([_blur_groups(su), _blur_groups(sv)], axis=1)
    groups, inverse = np.unique(keys, axis=0, return_inverse=True)
    image = np.zeros(grid.shape)
    for index, (ku, kv) in enumerate(groups):
        members = inverse.ravel() == index
        sigma_px = (
            _BLUR_STEP ** float(kv) / grid.pixel_nm,
            _BLUR_STEP ** float(ku) / grid.pixel_nm,
        )
        part = _histogram(grid, u[members], v[members], w[members])
        image += ndimage.gaussian_filter(part, sigma_px, mode="constant", truncate=3.5)
    return image

"""Per-particle values on the calibration's z grid, read at other depths.

Every row of ``z_grid`` (n, n_z) is the same increasing grid of piezo planes minus one shift
(the particle's tilt plane), so each point interpolates on the first row after undoing its row's
shift, without gathering whole rows. Outside a row's grid the end value is held.
"""

from __future__ import annotations

import numpy as np

__all__ = ["interp_rows", "row_weights"]


def row_weights(
    z_grid: np.ndarray, rows: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where :func:`interp_rows` reads each point: the rows, the upper plane index j and the
    weight w of plane j (1 − w of plane j − 1); computed once for every trace read at the same
    points (module notes)."""
    base = z_grid[0]
    u = z + (base[0] - z_grid[:, 0])[rows]
    j = np.clip(np.searchsorted(base, np.where(np.isfinite(u), u, -np.inf)), 1, base.size - 1)
    w = np.clip((u - base[j - 1]) / (base[j] - base[j - 1]), 0.0, 1.0)
    return rows, j, w


def interp_rows(
    z_grid: np.ndarray,
    values: np.ndarray,
    rows: np.ndarray,
    z: np.ndarray,
    at: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Linear interpolation of ``values[rows[k]]`` (on ``z_grid[rows[k]]``) at ``z[k]``;
    ``values`` (n, n_z) or (n, n_z, m): m values read at once, (len(z), m). ``at``:
    :func:`row_weights` of these rows and z, if already known."""
    rows, j, w = row_weights(z_grid, rows, z) if at is None else at
    w = w.reshape(w.shape + (1,) * (np.ndim(values) - 2))
    return (1 - w) * values[rows, j - 1] + w * values[rows, j]

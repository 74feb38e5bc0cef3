"""Per-ROI windows: the rows and columns of a ROI that a fit may see.

A ROI centred on an emitter near the frame's edge reaches past it. `latentz.localize` cuts such a
ROI whole (its pixels outside the frame NaN) and gives :func:`latentz.fit.fit_arrays` each ROI's
*window*, ``(row_start, row_stop, col_start, col_stop)`` in ROI pixels: the fit sees only the
window's pixels, so those outside are left out of the likelihood, and its Cramér–Rao bounds grow
as fewer pixels of the spot are seen. ROIs are fitted in groups that share a window, each group as
a stack of its windows' pixels: the kernels are the whole ROI's, and a ROI whose window is whole
is fitted exactly as without windows.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from latentz._shared.validate import check_array

__all__ = ["MIN_SIDE", "check_windows", "window_groups"]

#: Smallest window side (px) that is fitted; a narrower window's fit is reported as failed.
MIN_SIDE = 3


def check_windows(windows: Any, n: int, shape: tuple[int, int]) -> np.ndarray | None:
    """``windows`` as an (n, 4) int64 array inside ROIs of ``shape`` (h, w), or None when it is
    None or every window is the whole ROI."""
    if windows is None:
        return None
    values = check_array("windows", windows, ndim=2, dtype_kind="iu", allow_empty=True)
    h, w = shape
    if values.shape != (n, 4):
        raise ValueError(
            f"Expected `windows` of shape ({n}, 4) (row_start, row_stop, col_start, col_stop "
            f"per ROI), got {values.shape}."
        )
    values = values.astype(np.int64)
    r0, r1, c0, c1 = values.T
    if not np.all((r0 >= 0) & (r0 < r1) & (r1 <= h) & (c0 >= 0) & (c0 < c1) & (c1 <= w)):
        raise ValueError(
            f"Expected each window to be a non-empty range of rows within 0..{h} and of columns "
            f"within 0..{w} (row_start < row_stop, col_start < col_stop)."
        )
    whole = (r0 == 0) & (r1 == h) & (c0 == 0) & (c1 == w)
    return None if whole.all() else values


def window_groups(windows: np.ndarray) -> Iterator[tuple[np.ndarray, tuple[int, int, int, int]]]:
    """(rows, window) for each distinct window of ``windows`` (n, 4), rows in ascending order."""
    keys, inverse = np.unique(windows, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(1, len(keys)))
    for key, rows in zip(keys, np.split(order, bounds), strict=True):
        yield rows, tuple(int(v) for v in key)

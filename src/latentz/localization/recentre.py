"""Fit ROIs, then fit again those whose emitter lies on another pixel than the ROI's centre.

Both modes of :func:`latentz.localize` (full detection, :mod:`latentz.localization.movie`, and
tracking, :mod:`latentz.localization.follow`) centre each ROI on its fitted position, as
calibration centres its fixed ROI on the particle: the fitted widths and centre of a wide,
truncated spot depend on where the ROI sits, and a first guess (a detection peak, a prediction)
can be a pixel off for a defocused, asymmetric image. At the frame's edge the ROI is clipped to
the frame: its pixels outside are left out of the fit. The errors are then the sandwich's of each
final fit, in its own ROI.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from latentz.detect import roi_windows
from latentz.fit.api import FitResult, fit_arrays, replace_rows, with_sandwich

__all__ = ["Recentred", "fit_recentred"]


class Recentred(NamedTuple):
    """Final fits (``x, y`` in full-frame px) and the ROIs they were fitted in: first pixels
    ``row0, col0``, ``edge`` (clipped to the frame), the ROIs (n, size, size, photoelectrons,
    NaN outside the frame) and each ROI's window inside the frame (`latentz.detect.roi_windows`)."""

    fit: FitResult
    row0: np.ndarray
    col0: np.ndarray
    edge: np.ndarray
    rois: np.ndarray
    windows: np.ndarray


def fit_recentred(
    read: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    rois: np.ndarray,
    corners: tuple[np.ndarray, np.ndarray],
    centres: tuple[np.ndarray, np.ndarray],
    *,
    frame_shape: tuple[int, int],
    method: str,
    readnoise: float,
    windows: np.ndarray | None = None,
    init: np.ndarray | None = None,
    device: str = "auto",
) -> Recentred:
    """Fit ``rois`` (first pixels ``corners = (row0, col0)``, ``windows`` where clipped) from
    ``init`` (n, 7, ROI px; default the moment start), then fit again in the ROI centred on each
    fit that lands on another pixel. ``read(moved, row0, col0)`` returns the ROIs of the rows
    ``moved`` (boolean mask) at those first pixels; ``centres = (rows, cols)`` are the pixels
    the ROIs were placed on, kept where a fit is not finite. The refit starts from the first fit
    when ``init`` is given, else from the moment start."""
    rois = np.asarray(rois, np.float64)
    size = rois.shape[-1]
    row0, col0 = corners
    fit = fit_arrays(rois, method=method, readnoise=readnoise, init=init, windows=windows,
                     device=device)  # fmt: skip
    x, y = fit.params[:, 0] + col0, fit.params[:, 1] + row0
    ok = np.isfinite(x) & np.isfinite(y)
    rows = np.where(ok, np.rint(y), centres[0]).astype(np.int64)
    cols = np.where(ok, np.rint(x), centres[1]).astype(np.int64)
    new_row0, new_col0, windows, edge = roi_windows(rows, cols, size, frame_shape)
    moved = (new_row0 != row0) | (new_col0 != col0)
    if moved.any():
        again = read(moved, new_row0[moved], new_col0[moved])
        start = None
        if init is not None:
            start = fit.params[moved].copy()
            start[:, 0] += col0[moved] - new_col0[moved]
            start[:, 1] += row0[moved] - new_row0[moved]
        refit = fit_arrays(again, method=method, readnoise=readnoise, init=start,
                           windows=windows[moved], device=device)  # fmt: skip
        fit = replace_rows(fit, refit, moved)
        rois = rois.copy()
        rois[moved] = again
    fit = with_sandwich(fit, rois, method=method, readnoise=readnoise, windows=windows)
    params = fit.params.copy()
    params[:, 0] += new_col0
    params[:, 1] += new_row0
    return Recentred(fit._replace(params=params), new_row0, new_col0, edge, rois, windows)

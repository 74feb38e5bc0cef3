"""Fit ROIs, then fit again those whose emitter lies on another pixel than the ROI's centre.

Both modes of :func:`latentz.localize` (full detection, :mod:`latentz.localization.movie`, and
tracking, :mod:`latentz.localization.follow`) centre each ROI on its fitted position, as
calibration centres its fixed ROI on the particle: the fitted widths and centre of a wide,
truncated spot depend on where the ROI sits, and a first guess (a detection peak, a prediction)
can be a pixel off for a defocused, asymmetric image. At the frame's edge the ROI is clipped to
the frame: its pixels outside are left out of the fit. The errors are then the sandwich's of each
final fit, in its own ROI. Without starting values, each fit starts at the pixel its ROI was
placed on (:func:`latentz.fit.api.starts_at_peaks`), not at the ROI's brightest pixels, which may
be a brighter neighbour's.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from latentz.detect import roi_windows
from latentz.fit.api import (
    FitResult,
    fit_arrays,
    replace_rows,
    result_table,
    starts_at_peaks,
    with_sandwich,
)

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["SHIFT_PX", "Recentred", "fit_recentred", "on_calibration_pixels"]

#: Lateral shift (px) beyond which :func:`on_calibration_pixels` fits a spot again on its place.
SHIFT_PX = 0.5


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
    ``init`` (n, 7, ROI px), then fit again in the ROI centred on each fit that lands on another
    pixel, from the first fit. ``read(moved, row0, col0)`` returns the ROIs of the rows
    ``moved`` (boolean mask) at those first pixels; ``centres = (rows, cols)`` are the pixels
    the ROIs were placed on, kept where a fit is not finite. ``init`` defaults to the moment
    start with its peak on the pixel each ROI was placed on (`_placed`)."""
    rois = np.asarray(rois, np.float64)
    size = rois.shape[-1]
    row0, col0 = corners
    if init is None:
        init = starts_at_peaks(rois, _placed(centres, corners, windows, size), windows)
    fit = fit_arrays(rois, method=method, readnoise=readnoise, init=init, windows=windows,
                     device=device)  # fmt: skip
    x, y = fit.params[:, 0] + col0, fit.params[:, 1] + row0
    ok = np.isfinite(x) & np.isfinite(y)
    rows = np.where(ok, np.rint(y), centres[0]).astype(np.int64)
    cols = np.where(ok, np.rint(x), centres[1]).astype(np.int64)
    new_row0, new_col0, windows, edge = roi_windows(rows, cols, size, frame_shape)
    moved = (new_row0 != row0) | (new_col0 != col0)
    if moved.any():
        refit, again = _fit_again(
            read, moved, fit, (row0, col0), (new_row0, new_col0), windows, method=method,
            readnoise=readnoise, device=device,
        )  # fmt: skip
        fit = replace_rows(fit, refit, moved)
        rois = rois.copy()
        rois[moved] = again
    fit = with_sandwich(fit, rois, method=method, readnoise=readnoise, windows=windows)
    params = fit.params.copy()
    params[:, 0] += new_col0
    params[:, 1] += new_row0
    return Recentred(fit._replace(params=params), new_row0, new_col0, edge, rois, windows)


def on_calibration_pixels(
    done: Recentred,
    read: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    calibration: Calibration,
    *,
    frame_shape: tuple[int, int],
    method: str,
    readnoise: float,
    device: str = "auto",
) -> Recentred:
    """``done`` with each spot that ``calibration`` moves by more than :data:`SHIFT_PX` (its
    lateral shift Δx′(z), Δy′(z) at the z it reads) fitted again in the ROI centred on its
    corrected place, where calibration's ROI sat on the particle at that z; the rest as they
    were. A defocused spot that fills its ROI fits narrower or wider as the ROI moves, so it is
    read against the calibration's images only from the calibration's ROI. Below half a pixel
    both ROIs lie within a pixel of the place. Spots whose new ROI would be clipped by the
    frame's edge keep their fit; the new fits start from the old, with sandwich errors."""
    size = done.rois.shape[-1]
    table = result_table(done.fit)
    table.attrs["roi_size"] = size
    located = calibration.apply(table, errors=False)
    px = calibration.camera.pixel_size_nm
    x, y = done.fit.params[:, 0], done.fit.params[:, 1]
    place_x, place_y = located["x_nm"].to_numpy() / px, located["y_nm"].to_numpy() / px
    with np.errstate(invalid="ignore"):
        far = np.maximum(np.abs(x - place_x), np.abs(y - place_y)) > SHIFT_PX
    far &= located["in_range"].to_numpy(bool)
    half = size // 2
    rows = np.where(far, np.rint(place_y), done.row0 + half).astype(np.int64)
    cols = np.where(far, np.rint(place_x), done.col0 + half).astype(np.int64)
    new_row0, new_col0, windows, edge = roi_windows(rows, cols, size, frame_shape)
    moved = far & ~edge & ((new_row0 != done.row0) | (new_col0 != done.col0))
    if not moved.any():
        return done
    local = done.fit.params.copy()
    local[:, 0] -= done.col0
    local[:, 1] -= done.row0
    refit, again = _fit_again(
        read, moved, done.fit._replace(params=local), (done.row0, done.col0),
        (new_row0, new_col0), windows, method=method, readnoise=readnoise, device=device,
    )  # fmt: skip
    refit = with_sandwich(refit, again, method=method, readnoise=readnoise,
                          windows=windows[moved])  # fmt: skip
    params = refit.params.copy()
    params[:, 0] += new_col0[moved]
    params[:, 1] += new_row0[moved]
    rois = done.rois.copy()
    rois[moved] = again
    return Recentred(
        replace_rows(done.fit, refit._replace(params=params), moved),
        np.where(moved, new_row0, done.row0), np.where(moved, new_col0, done.col0),
        done.edge, rois, np.where(moved[:, None], windows, done.windows),
    )  # fmt: skip


def _fit_again(
    read: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    moved: np.ndarray,
    fit: FitResult,
    old: tuple[np.ndarray, np.ndarray],
    new: tuple[np.ndarray, np.ndarray],
    windows: np.ndarray,
    *,
    method: str,
    readnoise: float,
    device: str,
) -> tuple[FitResult, np.ndarray]:
    """The rows ``moved`` fitted in their ROIs at first pixels ``new = (row0, col0)``, read
    with ``read``, from ``fit`` (ROI px of the ROIs at ``old``) carried to the new ROIs; and
    those ROIs."""
    row0, col0 = new[0][moved], new[1][moved]
    again = read(moved, row0, col0)
    start = fit.params[moved].copy()
    start[:, 0] += old[1][moved] - col0
    start[:, 1] += old[0][moved] - row0
    refit = fit_arrays(again, method=method, readnoise=readnoise, init=start,
                       windows=windows[moved], device=device)  # fmt: skip
    return refit, again


def _placed(
    centres: tuple[np.ndarray, np.ndarray],
    corners: tuple[np.ndarray, np.ndarray],
    windows: np.ndarray | None,
    size: int,
) -> np.ndarray:
    """The pixels (n, 2; row, col in ROI px) that ROIs with first pixels ``corners`` were placed
    on, ``centres`` (full-frame px), moved into each ROI's window (the frame) where they lie
    outside it."""
    placed = np.column_stack([centres[0] - corners[0], centres[1] - corners[1]])
    if windows is None:
        return np.clip(placed, 0, size - 1)
    return np.clip(placed, windows[:, [0, 2]], windows[:, [1, 3]] - 1)

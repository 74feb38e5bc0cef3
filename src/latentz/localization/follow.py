"""Tracking mode of :func:`latentz.localize`: fit each emitter where its last positions predict it.

Frame by frame, in order. Every ``detect_every`` frames, and on any frame where a tracked fit is
lost, the whole frame is detected and fitted as :func:`latentz.localize` does. On the frames
between, each tracked emitter is fitted in the ROI centred on its predicted position, started
from its last fit, and only those ROIs are read (from a memory-mapped TIFF, only their bytes);
new emitters are looked for in a band along the frame's edge, where they enter.

Prediction: when at least three emitters were fitted in both of the last two frames, the rigid
motion (rotation and shift) between those frames, applied once more, as a body that turns at a
steady rate (a microgear); when that rigid motion does not describe the last step to within
`_RIGID_RMS_PX`, each emitter's own last step, applied once more.

A fit is lost when it did not converge, or when it lies more than half the ROI less one pixel
from its prediction (the emitter may then lie partly outside the ROI that was fitted). A ROI
whose fit lands on another pixel than the ROI's centre is cut again there and refitted by the
function full detection uses (:mod:`latentz.localization.recentre`), so that both modes fit each
emitter in the same ROI.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from latentz.camera import Camera
from latentz.detect import (
    band_noise,
    cut_photons,
    default_threshold,
    detect_arrays,
    roi_windows,
)
from latentz.fit.api import FitResult, result_table
from latentz.localization.recentre import fit_recentred

__all__ = ["localize_tracked"]

_RIGID_RMS_PX = 0.5


def rigid_step(before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Rotation ``R`` (2, 2), shift ``d`` (2,) with ``after ~ before @ R.T + d`` (least squares,
    Kabsch) for (k, 2) positions in px, and the rms residual in px."""
    cb, ca = before.mean(axis=0), after.mean(axis=0)
    u, _, vt = np.linalg.svd((before - cb).T @ (after - ca))
    rot = (u @ vt).T
    if np.linalg.det(rot) < 0:
        vt[-1] *= -1
        rot = (u @ vt).T
    shift = ca - cb @ rot.T
    rms = float(np.sqrt(np.mean(np.sum((before @ rot.T + shift - after) ** 2, axis=1))))
    return rot, shift, rms


def predict(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Predicted next positions (k, 2) of tracks at ``current`` (k, 2) px, whose positions one
    frame earlier are ``previous`` (NaN rows for tracks seen once)."""
    known = np.all(np.isfinite(previous), axis=1)
    if known.sum() >= 3:
        rot, shift, rms = rigid_step(previous[known], current[known])
        if rms <= _RIGID_RMS_PX:
            return current @ rot.T + shift
    out = current.copy()
    out[known] = 2.0 * current[known] - previous[known]
    return out


class _Source:
    """Reads frames or ROIs of one movie and converts them to photoelectrons."""

    def __init__(self, movie: Any, camera: Camera | None):
        self.movie = movie
        self.camera = camera
        self.shape = tuple(movie.shape[1:])

    def frame(self, t: int) -> np.ndarray:
        adu = np.asarray(self.movie[t])
        if self.camera is None:
            return adu.astype(np.float64)
        return self.camera.to_photons(adu)

    def rois(self, t: int, row0: np.ndarray, col0: np.ndarray, size: int) -> np.ndarray:
        """ROIs of frame ``t`` at the given corners; only their pixels are read."""
        frame = self.movie[t]
        if not isinstance(frame, np.ndarray):  # a dask array: read the frame once
            frame = np.asarray(frame)
        zero = np.zeros(len(row0), np.int64)
        return cut_photons(frame[None], zero, row0, col0, size, self.camera)

    def band(self, t: int, rows: slice, cols: slice) -> np.ndarray:
        """Photoelectrons of a rectangle of frame ``t``; only its pixels are read."""
        adu = np.asarray(self.movie[t][rows, cols])
        if self.camera is None:
            return adu.astype(np.float64)
        return self.camera.to_photons(adu, origin=(rows.start, cols.start))


def _fit_centred(
    source: _Source, t: int, xy: np.ndarray, size: int, method: str, readnoise: float,
    init: np.ndarray | None,
) -> tuple[FitResult, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Fit ROIs centred at ``xy`` (k, 2) px of frame ``t`` from ``init`` (k, 7, full-frame px;
    default the moment start), refit once where the fit lands on another pixel
    (`fit_recentred`). Returns the fit (x, y in full-frame px), row0, col0 and edge flags."""
    rows, cols = np.rint(xy[:, 1]).astype(np.int64), np.rint(xy[:, 0]).astype(np.int64)
    row0, col0, windows, _ = roi_windows(rows, cols, size, source.shape)
    start = None
    if init is not None:
        start = init.copy()
        start[:, 0] = xy[:, 0] - col0
        start[:, 1] = xy[:, 1] - row0
    done = fit_recentred(
        lambda _, r0, c0: source.rois(t, r0, c0, size), source.rois(t, row0, col0, size),
        (row0, col0), (rows, cols), frame_shape=source.shape, method=method,
        readnoise=readnoise, windows=windows, init=start,
    )  # fmt: skip
    return done.fit, done.row0, done.col0, done.edge


def _new(candidates: np.ndarray, known: np.ndarray, half: int) -> np.ndarray:
    """Candidates (k, 2) px more than ``half`` px (Chebyshev) from every known position and
    from every earlier candidate kept."""
    keep = np.zeros(len(candidates), bool)
    for k, xy in enumerate(candidates):
        taken = np.concatenate([known, candidates[:k][keep[:k]]])
        keep[k] = np.all(np.isfinite(xy)) and bool(np.all(np.abs(taken - xy).max(axis=1) > half))
    return keep


def _close_pairs(xy: np.ndarray, half: int) -> np.ndarray:
    """Another emitter within ``half`` px (Chebyshev) of each rounded position."""
    pix = np.rint(xy).astype(np.int64)
    gap = np.abs(pix[:, None, :] - pix[None, :, :]).max(axis=2)
    np.fill_diagonal(gap, half + 1)
    return (gap <= half).any(axis=1)


def _edge_bands(source: _Source, t: int, size: int) -> list[tuple[np.ndarray, ...]]:
    """The bands ``size`` px wide along the four edges of frame ``t`` (photoelectrons), in
    groups of one length (one group for a square frame): (bands (k, size, length), the frame
    row or column of each band's first line (k,), transposed (k,)). The left and right bands are
    transposed to lie like the top and bottom ones."""
    h, w = source.shape
    top = source.band(t, slice(0, size), slice(0, w))
    bottom = source.band(t, slice(h - size, h), slice(0, w))
    left = source.band(t, slice(0, h), slice(0, size)).T
    right = source.band(t, slice(0, h), slice(w - size, w)).T
    groups = [([top, bottom], [0, h - size], False), ([left, right], [0, w - size], True)]
    if h == w:
        groups = [([top, bottom, left, right], [0, h - size, 0, w - size], [0, 0, 1, 1])]
    return [
        (np.stack(bands), np.asarray(first), np.broadcast_to(np.asarray(flip, bool), len(bands)))
        for bands, first, flip in groups
    ]


def _entering(
    groups: list[tuple[np.ndarray, ...]], noise: list[np.ndarray], size: int, threshold: float,
    sigma: float,
) -> np.ndarray:  # fmt: skip
    """(x, y) px of the detections in the edge bands of `_edge_bands`, whose band-passed noise
    is ``noise`` (`latentz.detect.band_noise`, one array per group)."""
    found = []
    for (bands, first, transposed), group_noise in zip(groups, noise, strict=True):
        det = detect_arrays(bands, roi_size=size, threshold=threshold, sigma=sigma,
                            noise=group_noise)  # fmt: skip
        across = det.row + first[det.frame]
        flip = transposed[det.frame]
        x = np.where(flip, across, det.col)
        y = np.where(flip, det.col, across)
        found.append(np.column_stack([x, y]).astype(np.float64))
    return np.concatenate(found)


def localize_tracked(
    movie: Any,
    full_frame: Any,
    *,
    camera: Camera | None,
    roi_size: int,
    threshold: float | None,
    method: str,
    sigma: float,
    detect_every: int,
    progress: bool = False,
) -> pd.DataFrame:
    """Localize a movie in tracking mode (see the module docstring); the table of `localize`.

    ``full_frame(t)`` detects and fits frame ``t`` and returns its table of `localize` (the
    full-detection path, shared with it). ``snr`` is NaN on
    rows fitted from a prediction: no detection scored them.
    """
    source = _Source(movie, camera)
    readnoise = camera.readnoise if camera is not None else 0.0
    half = roi_size // 2
    band_threshold = default_threshold(*source.shape) if threshold is None else threshold
    tables: list[pd.DataFrame] = []
    tracked: list[tuple[int, FitResult, np.ndarray, np.ndarray]] = []
    current = previous = np.empty((0, 2))
    params = np.empty((0, 7))
    band_noise_known = None
    for t in tqdm(range(movie.shape[0]), unit="frame", disable=not progress):
        full = t % detect_every == 0 or len(current) == 0
        if not full:
            guess = predict(previous, current)
            fit, _, _, edge = _fit_centred(source, t, guess, roi_size, method, readnoise, params)
            xy = fit.params[:, :2]
            lost = ~fit.converged | (np.abs(xy - guess).max(axis=1) > half - 1)
            full = bool(lost.any())
        if not full:
            bands = _edge_bands(source, t, roi_size)
            if band_noise_known is None:  # once per full detection: each band's pixel noise
                band_noise_known = [band_noise(b, sigma=sigma) for b, _, _ in bands]
            entering = _entering(bands, band_noise_known, roi_size, band_threshold, sigma)
            entering = entering[_new(entering, xy, half)]
            if len(entering):
                extra, _, _, extra_edge = _fit_centred(
                    source, t, entering, roi_size, method, readnoise, None
                )
                # a maximum on the wing of a tracked spot fits that spot
                keep = extra.converged & _new(extra.params[:, :2], xy, half)
                fit = FitResult(
                    *(np.concatenate([a, b[keep]]) for a, b in zip(fit, extra, strict=True))
                )
                edge = np.concatenate([edge, extra_edge[keep]])
            tracked.append((t, fit, edge, _close_pairs(fit.params[:, :2], half)))
            previous = np.concatenate(
                [current, np.full((len(fit.params) - len(current), 2), np.nan)]
            )
            current, params = fit.params[:, :2].copy(), fit.params.copy()
            continue
        table = full_frame(t)
        tables.append(table)
        band_noise_known = None
        good = table[table["converged"]]
        found = good[["x", "y"]].to_numpy()
        previous = _history(found, previous, current, half)
        current, params = found, good[["x", "y", "amplitude", "background", "wx", "wy", "rho"]]
        params = params.to_numpy()
    if tracked:
        tables.append(_tracked_table(tracked))
    table = pd.concat(tables, ignore_index=True)
    return table.sort_values("frame", kind="stable", ignore_index=True)


def _tracked_table(tracked: list[tuple[int, FitResult, np.ndarray, np.ndarray]]) -> pd.DataFrame:
    """One table of the rows fitted from predictions: (frame, fit, edge, close_pair) per frame."""
    fits = (f for _, f, _, _ in tracked)
    fit = FitResult(*(np.concatenate(parts) for parts in zip(*fits, strict=True)))
    frame = np.concatenate([np.full(len(f.params), t) for t, f, _, _ in tracked])
    return result_table(
        fit, frame=frame, snr=np.full(len(frame), np.nan),
        edge=np.concatenate([e for _, _, e, _ in tracked]),
        close_pair=np.concatenate([c for _, _, _, c in tracked]), pair=-1, merged=False,
    )  # fmt: skip


def _history(
    found: np.ndarray, previous: np.ndarray, current: np.ndarray, radius: float
) -> np.ndarray:
    """Last positions (k, 2) of the emitters ``found`` by a full detection, NaN where unknown.

    Each found emitter is paired with the track whose prediction is its mutual nearest
    neighbour: within ``radius`` px when the track's motion is known, at any distance when it is
    not (its prediction is its last position, and the body may have moved far since).
    """
    out = np.full_like(found, np.nan)
    if len(current) == 0 or len(found) == 0:
        return out
    guess = predict(previous, current)
    moving = np.all(np.isfinite(previous), axis=1) | _rigid_known(previous)
    dist = np.hypot(*(found[:, None, :] - guess[None, :, :]).transpose(2, 0, 1))
    nearest = dist.argmin(axis=1)
    mutual = dist.argmin(axis=0)[nearest] == np.arange(len(found))
    close = dist[np.arange(len(found)), nearest] <= radius
    paired = mutual & (close | ~moving[nearest])
    out[paired] = current[nearest[paired]]
    return out


def _rigid_known(previous: np.ndarray) -> np.ndarray:
    """True for every track when the rigid prediction applies (3 tracks with history)."""
    known = np.all(np.isfinite(previous), axis=1)
    return np.full(len(previous), known.sum() >= 3)

"""Drift from fiducials: emitters seen in most frames that stay put (beads, static particles),
picked automatically. Each one's track is its nearest localization in every frame; the drift of a
frame is the mean offset of the fiducials from their own positions."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["pick_fiducials", "fiducial_drift"]


def _candidates(xy: np.ndarray, n_frames: int, radius_nm: float, min_fraction: float):
    """Places (nm) where a 3 x 3 block of bins of ``radius_nm`` holds at least
    ``min_fraction * n_frames`` localizations and is a local maximum of that count: the median
    position of the block's localizations, one per place."""
    origin = xy.min(axis=0)
    cells = np.floor((xy - origin) / radius_nm).astype(np.int64)
    counts = np.zeros(tuple(cells.max(axis=0) + 1))
    np.add.at(counts, (cells[:, 0], cells[:, 1]), 1.0)
    near = np.rint(ndimage.uniform_filter(counts, 3, mode="constant") * 9)
    peaks = (near >= min_fraction * n_frames) & (near == ndimage.maximum_filter(near, 3))
    places: list[np.ndarray] = []
    for i, j in zip(*np.nonzero(peaks), strict=True):
        block = (np.abs(cells[:, 0] - i) <= 1) & (np.abs(cells[:, 1] - j) <= 1)
        place = np.median(xy[block], axis=0)
        if all(np.hypot(*(place - other)) > radius_nm for other in places):
            places.append(place)
    return places


def _track(
    xyz: np.ndarray, frame_index: np.ndarray, n_frames: int, centre: np.ndarray, radius_nm: float
) -> np.ndarray:
    """(n_frames, 3) positions of the localization nearest ``centre`` within ``radius_nm``
    laterally in each frame (NaN where none)."""
    distance = np.hypot(*(xyz[:, :2] - centre).T)
    near = np.flatnonzero(distance <= radius_nm)
    near = near[np.argsort(distance[near])]
    _, first = np.unique(frame_index[near], return_index=True)
    chosen = near[first]
    track = np.full((n_frames, 3), np.nan)
    track[frame_index[chosen]] = xyz[chosen]
    return track


def pick_fiducials(
    xyz: np.ndarray,
    frame_index: np.ndarray,
    n_frames: int,
    *,
    radius_nm: float,
    min_fraction: float,
) -> np.ndarray:
    """Tracks (n_fiducials, n_frames, 3) of the emitters present (within ``radius_nm`` of one
    place) in at least ``min_fraction`` of the frames; a clear error when there are none."""
    centres = _candidates(xyz[:, :2], n_frames, radius_nm, min_fraction)
    tracks = []
    for centre in centres:
        track = _track(xyz, frame_index, n_frames, centre, radius_nm)
        centre = np.nanmedian(track[:, :2], axis=0)  # re-centre on the emitter and track again
        track = _track(xyz, frame_index, n_frames, centre, radius_nm)
        if np.isfinite(track[:, 0]).mean() >= min_fraction:
            tracks.append(track)
    if not tracks:
        raise ValueError(
            f"No fiducial found: no emitter is seen in {min_fraction:.0%} of the frames within "
            f"{radius_nm:g} nm of one place. Use method='rcc', or a larger fiducial radius if "
            "the drift is larger."
        )
    return np.array(tracks)


def _common_offset(tracks: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drift per frame (mean over the kept fiducials of their offsets from their own positions)
    and each fiducial's position, alternately re-estimated."""
    drift = np.zeros(tracks.shape[1:])
    for _ in range(3):
        home = np.nanmedian(tracks - drift, axis=1)
        with np.errstate(invalid="ignore"):
            drift = np.nanmean(tracks[keep] - home[keep, None, :], axis=0)
        drift = np.nan_to_num(drift)
    return drift, home


def fiducial_drift(tracks: np.ndarray, *, smooth_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Drift per frame (n_frames, 3) from fiducial tracks, and which fiducials stayed put.

    A fiducial whose RMS residual from the common drift exceeds 3 times the median (with three or
    more fiducials) moved on its own and is dropped. Frames without any fiducial are
    interpolated; the drift is then averaged over ``smooth_frames`` frames."""
    keep = np.ones(len(tracks), dtype=bool)
    drift, home = _common_offset(tracks, keep)
    if len(tracks) >= 3:
        residual = tracks - home[:, None, :] - drift
        rms = np.sqrt(np.nanmean(np.sum(residual[..., :2] ** 2, axis=2), axis=1))
        keep = rms <= 3.0 * np.median(rms)
        drift, home = _common_offset(tracks, keep)
    seen = np.isfinite(tracks[keep, :, 0]).any(axis=0)
    frames = np.arange(tracks.shape[1])
    for axis in range(3):
        drift[:, axis] = np.interp(frames, frames[seen], drift[seen, axis])
    if smooth_frames > 1:
        drift = ndimage.uniform_filter1d(drift, smooth_frames, axis=0, mode="nearest")
    return drift, keep

"""Drift by redundant cross-correlation (RCC): images of frame segments are cross-correlated in
every pair, and the segments' drifts are the least-squares solution of all the pairwise shifts,
with the pairs that disagree dropped. Lateral drift from x-y images, then axial drift from x-z and
y-z images of the laterally corrected segments."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import fft

from latentz.analysis.histograms import Grid, grid_for, splat

__all__ = ["segment_of", "rcc_segments"]


def segment_of(frames: np.ndarray, segment_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Segment index of each localization (blocks of ``segment_frames`` frames from the first)
    and each segment's centre, its localizations' mean frame. Empty blocks are skipped."""
    block = (frames - frames.min()) // segment_frames
    _, index = np.unique(block, return_inverse=True)
    centres = np.bincount(index, weights=frames) / np.bincount(index)
    return index, centres


def _spectra(grid: Grid, u, v, seg, n_seg, sigma_u, sigma_v) -> list[np.ndarray]:
    """The 2D Fourier transform (real input) of each segment's image on ``grid``."""
    return [
        fft.rfft2(splat(grid, u[seg == s], v[seg == s], sigma_u_nm=sigma_u, sigma_v_nm=sigma_v))
        for s in range(n_seg)
    ]


def _peak(correlation: np.ndarray) -> tuple[float, float]:
    """Shift (rows, columns) of the correlation's highest peak, refined by a parabola through
    the logarithm of it and its neighbours on each axis (exact for a Gaussian peak)."""
    row, col = np.unravel_index(np.argmax(correlation), correlation.shape)
    shift = []
    for axis, at in ((0, row), (1, col)):
        n = correlation.shape[axis]
        around = [(at - 1) % n, at, (at + 1) % n]
        line = correlation[around, col] if axis == 0 else correlation[row, around]
        low, mid, high = np.log(np.maximum(line, line.max() * 1e-6))
        curvature = low - 2 * mid + high
        offset = 0.5 * (low - high) / curvature if curvature < 0 else 0.0
        shift.append((at + offset + n / 2) % n - n / 2)  # wrap to [-n/2, n/2)
    return shift[0], shift[1]


def _pair_shifts(
    spectra: list[np.ndarray], shape: tuple[int, int], pixel_nm: float
) -> tuple[np.ndarray, np.ndarray]:
    """For every pair i < j, (i, j) and how far segment j's content moved from segment i's,
    (du, dv) in nm, from the peak of their cross-correlation (scipy.fft)."""
    pairs, shifts = [], []
    for i in range(len(spectra)):
        for j in range(i + 1, len(spectra)):
            correlation = fft.irfft2(spectra[j] * np.conj(spectra[i]), s=shape)
            dv, du = _peak(correlation)
            pairs.append((i, j))
            shifts.append((du * pixel_nm, dv * pixel_nm))
    return np.array(pairs), np.array(shifts)


def _solve(pairs: np.ndarray, shifts: np.ndarray, n_seg: int, tolerance_nm: float) -> np.ndarray:
    """Drift of each segment (segment 0 at zero) from the pairwise shifts d_ij = r_j - r_i by
    least squares; pairs whose residual exceeds ``tolerance_nm`` (and 3 robust sigmas) are
    dropped and the rest solved again, as long as every segment keeps a pair."""
    design = np.zeros((len(pairs), n_seg))
    design[np.arange(len(pairs)), pairs[:, 1]] = 1.0
    design[np.arange(len(pairs)), pairs[:, 0]] = -1.0
    keep = np.ones(len(pairs), dtype=bool)
    for _ in range(2):
        drift = np.linalg.lstsq(design[keep][:, 1:], shifts[keep], rcond=None)[0]
        drift = np.vstack([np.zeros((1, shifts.shape[1])), drift])
        residual = np.linalg.norm(design @ drift - shifts, axis=1)
        spread = 1.4826 * np.median(residual)
        trial = residual <= max(tolerance_nm, 3.0 * spread)
        if np.all(np.abs(design[trial]).sum(axis=0) > 0):
            keep = trial
    return drift


def _lateral(xyz: pd.DataFrame, seg: np.ndarray, n_seg: int, pixel_nm: float, blur_nm: float):
    grid = grid_for(xyz["x_nm"].to_numpy(), xyz["y_nm"].to_numpy(), pixel_nm, margin_nm=3 * blur_nm)
    spectra = _spectra(
        grid, xyz["x_nm"].to_numpy(), xyz["y_nm"].to_numpy(), seg, n_seg, blur_nm, blur_nm
    )
    pairs, shifts = _pair_shifts(spectra, grid.shape, pixel_nm)
    return _solve(pairs, shifts, n_seg, pixel_nm)


def _axial(
    xyz: pd.DataFrame,
    seg: np.ndarray,
    n_seg: int,
    pixel_nm: float,
    blur_nm: float,
    blur_z_nm: float,
) -> np.ndarray:
    """z drift of each segment from its x-z and y-z images (the two estimates averaged)."""
    z = xyz["z_nm"].to_numpy()
    estimates = []
    for axis in ("x_nm", "y_nm"):
        u = xyz[axis].to_numpy()
        grid = grid_for(u, z, pixel_nm, margin_nm=3 * max(blur_nm, blur_z_nm))
        spectra = _spectra(grid, u, z, seg, n_seg, blur_nm, blur_z_nm)
        pairs, shifts = _pair_shifts(spectra, grid.shape, pixel_nm)
        estimates.append(shifts[:, 1])
    return _solve(pairs, np.mean(estimates, axis=0)[:, None], n_seg, pixel_nm)[:, 0]


def rcc_segments(
    xyz: pd.DataFrame,
    frames: np.ndarray,
    *,
    segment_frames: int,
    pixel_nm: float,
    blur_nm: float,
    blur_z_nm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Segment centres (frames) and the drift of each segment, (n_segments, 3) x, y, z in nm
    relative to the first segment. ``xyz`` holds x_nm, y_nm (finite) and z_nm of each row of
    ``frames``; images have ``pixel_nm`` pixels and Gaussian blur ``blur_nm`` (laterally) and
    ``blur_z_nm`` (axially). z drift is NaN where some segment has no finite z (2D data)."""
    seg, centres = segment_of(frames, segment_frames)
    n_seg = len(centres)
    if n_seg < 3:
        raise ValueError(
            f"RCC needs at least 3 segments of frames, got {n_seg} with segment_frames="
            f"{segment_frames}: give a smaller segment_frames."
        )
    lateral = _lateral(xyz, seg, n_seg, pixel_nm, blur_nm)
    moved = xyz.copy()
    moved["x_nm"] -= lateral[seg, 0]
    moved["y_nm"] -= lateral[seg, 1]
    with_z = np.isfinite(moved["z_nm"].to_numpy())
    axial = np.full(n_seg, np.nan)
    if np.unique(seg[with_z]).size == n_seg:
        axial = _axial(moved[with_z], seg[with_z], n_seg, pixel_nm, blur_nm, blur_z_nm)
    return centres, np.column_stack([lateral, axial])

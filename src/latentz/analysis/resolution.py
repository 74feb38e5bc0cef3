"""Fourier ring correlation (FRC): the resolution of a localization image as the spatial
frequency where two independent halves of the data stop agreeing (correlation 1/7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import fft
from scipy.signal.windows import tukey

from latentz._shared.validate import check_choice, check_int, check_positive
from latentz.analysis.histograms import grid_for, positions, splat

__all__ = ["FRC", "frc", "frc_halves", "HALVES"]

HALVES = ("blocks", "random", "odd_even")

#: The FRC threshold of a resolved frequency.
THRESHOLD = 1.0 / 7.0

#: Rings are this many frequency steps wide.
_RING_STEPS = 2


@dataclass(frozen=True)
class FRC:
    """The result of :func:`frc`: the resolution (nm; NaN when the curve never falls below the
    threshold) and the curve, ``q_per_nm`` (ring centres, 1/nm) against ``frc``."""

    resolution_nm: float
    curve: pd.DataFrame
    split: str
    pixel_nm: float

    def __float__(self) -> float:
        return self.resolution_nm

    def figure(self):
        """The FRC curve with the 1/7 threshold and the resolution marked."""
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.6))
        ax.plot(self.curve["q_per_nm"], self.curve["frc"], lw=1.2, label="FRC")
        ax.axhline(THRESHOLD, color="0.4", ls="--", lw=1, label="1/7")
        if np.isfinite(self.resolution_nm):
            ax.axvline(1 / self.resolution_nm, color="C3", lw=1)
            label = f"resolution {self.resolution_nm:.1f} nm"
        else:
            label = "the curve stays above 1/7: resolution finer than 2 pixels"
        ax.set(
            xlabel="spatial frequency (1/nm)",
            ylabel="Fourier ring correlation",
            ylim=(-0.1, 1.05),
            title=f"{label} (halves: {self.split}, {self.pixel_nm:g} nm pixels)",
        )
        ax.legend(fontsize=8)
        fig.tight_layout()
        return fig


def frc_halves(frames: np.ndarray, split: str, *, n_blocks: int = 20, seed: int = 0) -> np.ndarray:
    """Which half (False, True) each localization goes to: ``"blocks"`` cuts the frames into
    ``n_blocks`` blocks of consecutive frames, half of them (at random) to each side;
    ``"random"`` each localization at random; ``"odd_even"`` by frame parity."""
    check_choice("split", split, HALVES)
    rng = np.random.default_rng(seed)
    if split == "odd_even":
        return frames % 2 == 1
    if split == "random":
        return rng.random(len(frames)) < 0.5
    first, last = frames.min(), frames.max()
    block = ((frames - first) * n_blocks // (last - first + 1)).astype(np.int64)
    sides = rng.permutation(np.arange(n_blocks) % 2 == 1)
    return sides[block]


def _ring_sums(a: np.ndarray, b: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
    """Per ring of ``_RING_STEPS`` frequency steps: sum of Re(A B*), |A|^2, |B|^2 (rfft2 half
    plane of square images of side ``n``)."""
    fa, fb = fft.rfft2(a), fft.rfft2(b)
    ky = fft.fftfreq(n) * n
    kx = fft.rfftfreq(n) * n
    ring = (np.hypot(ky[:, None], kx[None, :]) / _RING_STEPS).astype(np.int64).ravel()
    n_rings = n // (2 * _RING_STEPS)
    sums = [
        np.bincount(ring, weights=w.ravel(), minlength=n_rings + 2)[:n_rings]
        for w in (np.real(fa * np.conj(fb)), np.abs(fa) ** 2, np.abs(fb) ** 2)
    ]
    return tuple(sums)


def _crossing(q: np.ndarray, curve: np.ndarray) -> float:
    """1 / the first frequency (after the curve was above it) where ``curve`` falls below 1/7,
    linearly interpolated; NaN if it never does."""
    above = np.flatnonzero(curve >= THRESHOLD)
    if above.size == 0:
        return np.nan
    below = np.flatnonzero((curve < THRESHOLD) & (np.arange(curve.size) > above[0]))
    if below.size == 0:
        return np.nan
    k = below[0]
    fraction = (curve[k - 1] - THRESHOLD) / (curve[k - 1] - curve[k])
    return float(1.0 / (q[k - 1] + fraction * (q[k] - q[k - 1])))


def frc(
    locs: pd.DataFrame,
    *,
    pixel_nm: float = 5.0,
    split: str = "blocks",
    n_blocks: int = 20,
    seed: int = 0,
) -> FRC:
    """Fourier ring correlation of two halves of the localizations (x_nm, y_nm).

    The halves (:func:`frc_halves`, ``split``) are binned into square images of ``pixel_nm``
    pixels (no blur), tapered at the edges (Tukey window), and correlated ring by ring in
    Fourier space; the curve is smoothed over three rings. The resolution is 1 / the frequency
    where the curve first falls below 1/7. A half that sees an emitter's other localizations
    correlates with the other half at all frequencies, so the "random" split (each localization
    at random) reports a finer resolution than "blocks" for emitters seen several times.
    """
    pixel_nm = check_positive("pixel_nm", pixel_nm)
    n_blocks = check_int("n_blocks", n_blocks, minimum=2)
    used = positions(locs, ("frame", "x_nm", "y_nm"))
    if len(used) < 100:
        raise ValueError(f"FRC needs at least 100 localizations with positions, got {len(used)}.")
    side = frc_halves(
        used["frame"].to_numpy().astype(np.int64), split, n_blocks=n_blocks, seed=seed
    )
    x, y = used["x_nm"].to_numpy(), used["y_nm"].to_numpy()
    span = max(np.ptp(x), np.ptp(y))
    grid = grid_for(x, y, pixel_nm, extent=(x.min(), x.min() + span, y.min(), y.min() + span))
    n = grid.n_u
    window = np.outer(tukey(n, 0.25), tukey(n, 0.25))
    halves = [splat(grid, x[side == s], y[side == s]) * window for s in (False, True)]
    cross, power_a, power_b = (
        np.convolve(s, np.ones(3), mode="same") for s in _ring_sums(*halves, n)
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        curve = cross / np.sqrt(power_a * power_b)
    q = (np.arange(curve.size) + 0.5) * _RING_STEPS / (n * pixel_nm)
    keep = np.arange(curve.size) > 0  # the ring holding zero frequency is the mean, not detail
    table = pd.DataFrame({"q_per_nm": q[keep], "frc": curve[keep]})
    return FRC(_crossing(q[keep], curve[keep]), table, split, pixel_nm)

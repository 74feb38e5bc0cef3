"""Test frames from a measured PSF: bead images through focus, placed at any sub-pixel position.

:class:`BeadPSF` averages the images of a few beads of a through-focus stack, each centred on its
true position, into one image per plane that sums to one. An emitter at (x, y, z) is that image,
interpolated linearly between the two nearest planes and shifted by the sub-pixel part of its
position in the Fourier domain, times its photons. The Fourier shift is exact for images that
are band-limited below the sampling's Nyquist frequency: a pixel-integrated optical PSF is, when
the optics' cutoff 2 NA / λ is below 1 / (2 × pixel size) (5 µm⁻¹ for 100 nm pixels).

The measured images carry the stack's noise. Averaging ``k`` beads of ``N`` photons each leaves a
per-pixel noise in the unit-sum image of about ``sqrt(p / (k N))`` (``p`` the pixel's share of
the light) plus the background's; rendered at ``n`` photons it is ``sqrt(n / (k N))`` of the
emitter's own shot noise, which is small for ``n`` well below ``k N``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from latentz._shared.validate import check_array, check_int
from latentz.simulate._render import add_patches

__all__ = ["BeadPSF"]


def _shift(images: np.ndarray, dx_px: np.ndarray, dy_px: np.ndarray) -> np.ndarray:
    """``images`` (n, s, s) moved by (dx, dy) pixels each (x = column), by a Fourier phase ramp
    (periodic: the images must fall to background at their edges)."""
    size = images.shape[-1]
    k = np.fft.fftfreq(size)
    ramp = np.exp(
        -2j
        * np.pi
        * (dy_px[:, None, None] * k[None, :, None] + dx_px[:, None, None] * k[None, None, :])
    )
    return np.fft.ifft2(np.fft.fft2(images) * ramp).real


@dataclass(frozen=True)
class BeadPSF:
    """A measured PSF: one unit-sum image per plane, the true centre on the central pixel.

    Attributes
    ----------
    z_nm : ndarray (n_z,)
        Axial position of each plane, strictly increasing, nm.
    images : ndarray (n_z, s, s)
        The PSF at each plane (s odd), background removed, each summing to one.
    """

    z_nm: np.ndarray
    images: np.ndarray

    @classmethod
    def from_stack(
        cls,
        photons: np.ndarray,
        z_nm: np.ndarray,
        centres_px: np.ndarray,
        *,
        size: int = 31,
    ) -> BeadPSF:
        """Average the beads at ``centres_px`` (k, 2: x = column, y = row, pixels) of a stack in
        photons (n_z, H, W) at planes ``z_nm``. Each bead's ``size`` × ``size`` window loses the
        median of its border (the local background), is shifted so that the bead's true centre
        lies on the central pixel, and is added; each plane is then scaled to sum to one."""
        stack = check_array("photons", photons, ndim=3).astype(np.float64)
        z = np.asarray(z_nm, dtype=np.float64).reshape(-1)
        if z.size != stack.shape[0] or np.any(np.diff(z) <= 0):
            raise ValueError(
                f"Expected `z_nm` to be {stack.shape[0]} strictly increasing values, one per "
                f"plane; got {z.size}."
            )
        centres = check_array("centres_px", centres_px, ndim=2).astype(np.float64)
        size = check_int("size", size, minimum=3)
        if size % 2 == 0 or centres.shape[1] != 2:
            raise ValueError(
                f"Expected an odd `size` and `centres_px` of shape (k, 2); got size {size} and "
                f"shape {centres.shape}."
            )
        half = size // 2
        total = np.zeros((z.size, size, size))
        for x, y in centres:
            col, row = int(round(x)), int(round(y))
            if not (half <= row < stack.shape[1] - half and half <= col < stack.shape[2] - half):
                raise ValueError(
                    f"The bead at x={x:.1f}, y={y:.1f} px lies within {half} px of the edge of "
                    f"the {stack.shape[1]} x {stack.shape[2]} px stack: use a smaller `size`."
                )
            win = stack[:, row - half : row + half + 1, col - half : col + half + 1]
            border = np.concatenate(
                [win[:, 0], win[:, -1], win[:, 1:-1, 0], win[:, 1:-1, -1]], axis=1
            )
            win = win - np.median(border, axis=1)[:, None, None]
            total += _shift(win, np.full(z.size, col - x), np.full(z.size, row - y))
        total /= total.sum(axis=(1, 2), keepdims=True)
        total.setflags(write=False)
        return cls(z_nm=z, images=total)

    def image(self, x_px: np.ndarray, y_px: np.ndarray, z_nm: np.ndarray) -> np.ndarray:
        """Unit-sum images (n, s, s) of emitters at ``z_nm`` whose centres lie at (x, y) pixels
        from each image's central pixel (sub-pixel offsets, within ±0.5 px for accuracy)."""
        z = np.asarray(z_nm, dtype=np.float64).reshape(-1)
        if np.any(z < self.z_nm[0]) or np.any(z > self.z_nm[-1]):
            raise ValueError(
                f"Expected every z within the measured {self.z_nm[0]:g}…{self.z_nm[-1]:g} nm; "
                f"got {z.min():g}…{z.max():g} nm."
            )
        upper = np.clip(np.searchsorted(self.z_nm, z, side="right"), 1, self.z_nm.size - 1)
        w = (z - self.z_nm[upper - 1]) / (self.z_nm[upper] - self.z_nm[upper - 1])
        mixed = (1 - w)[:, None, None] * self.images[upper - 1] + w[:, None, None] * self.images[
            upper
        ]
        x = np.asarray(x_px, dtype=np.float64).reshape(-1)
        y = np.asarray(y_px, dtype=np.float64).reshape(-1)
        return _shift(mixed, x, y)

    def render(
        self,
        emitters: pd.DataFrame,
        *,
        n_frames: int,
        frame_shape: tuple[int, int],
        background: float,
    ) -> np.ndarray:
        """Expected photons per pixel (n_frames, H, W): a uniform ``background`` plus every
        emitter (columns ``frame``, ``x``, ``y`` in pixels, ``z_nm``, ``photons``), clipped at
        zero where the measured image's noise would make a pixel negative."""
        x = emitters["x"].to_numpy(np.float64)
        y = emitters["y"].to_numpy(np.float64)
        col, row = np.round(x), np.round(y)
        images = self.image(x - col, y - row, emitters["z_nm"].to_numpy(np.float64))
        half = self.images.shape[-1] // 2
        expected = np.full((int(n_frames), *frame_shape), float(background))
        add_patches(
            expected,
            emitters["frame"].to_numpy(np.int64),
            images,
            np.stack([row - half, col - half], axis=1).astype(np.int64),
            emitters["photons"].to_numpy(np.float64),
        )
        return np.maximum(expected, 0.0, out=expected)

"""Camera model: offset, gain, read noise, pixel size and flatfield.

The flatfield follows the paper's Results, "A flatfield correction".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from latentz._shared.validate import check_array, check_finite, check_positive

__all__ = ["Camera"]


@dataclass(frozen=True)
class Camera:
    """A linear camera that turns photoelectrons into ADU.

    Parameters
    ----------
    offset : float
        Baseline added to every pixel, in ADU.
    gain : float
        Photoelectrons per ADU (> 0). A pixel of ``adu`` counts holds
        ``(adu - offset) * gain / flatfield`` photoelectrons.
    readnoise : float
        Read-noise standard deviation, in photoelectrons (>= 0).
    pixel_size_nm : float
        Pixel size in the sample plane, in nm (> 0).
    flatfield : ndarray (H, W) or None
        Relative sensitivity of each pixel (mean about 1); ``None`` means uniform.

    Examples
    --------
    >>> cam = Camera(offset=100.0, gain=0.5)
    >>> float(cam.to_photons(np.array([300.0]))[0])
    100.0
    """

    offset: float = 100.0
    gain: float = 0.5
    readnoise: float = 1.5
    pixel_size_nm: float = 130.0
    flatfield: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", check_finite("offset", self.offset))
        object.__setattr__(self, "gain", check_positive("gain", self.gain))
        object.__setattr__(
            self, "readnoise", check_positive("readnoise", self.readnoise, allow_zero=True)
        )
        object.__setattr__(
            self, "pixel_size_nm", check_positive("pixel_size_nm", self.pixel_size_nm)
        )
        if self.flatfield is not None:
            flat = check_array("flatfield", self.flatfield, ndim=2).astype(np.float64)
            if not np.all(np.isfinite(flat)) or np.any(flat <= 0):
                raise ValueError("Expected `flatfield` to be finite and > 0 everywhere.")
            flat.setflags(write=False)
            object.__setattr__(self, "flatfield", flat)

    def to_photons(self, adu: Any, *, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Convert ADU to photoelectrons: ``(adu - offset) * gain / flatfield``.

        ``adu`` has shape (..., h, w). ``origin`` is the (row, column) of its first pixel in the
        flatfield, for ROIs cut from a larger frame.
        """
        arr = check_array("adu", adu, ndim=range(2, 5)).astype(np.float64)
        photons = (arr - self.offset) * self.gain
        flat = self.flatfield_region(arr.shape[-2:], origin=origin)
        return photons if flat is None else photons / flat

    def flatfield_region(
        self, shape: tuple[int, int], *, origin: tuple[int, int] = (0, 0)
    ) -> np.ndarray | None:
        """The flatfield under an image of ``shape`` (rows, columns) whose first pixel lies at
        ``origin`` (row, column) on the sensor; None for a uniform camera."""
        if self.flatfield is None:
            return None
        (r0, c0), (h, w) = origin, shape
        flat = self.flatfield[r0 : r0 + h, c0 : c0 + w]
        if flat.shape != (h, w):
            raise ValueError(
                f"Image of shape {(h, w)} at origin {origin} does not fit inside the "
                f"flatfield of shape {self.flatfield.shape}."
            )
        return flat

    def to_adu(self, photons: Any) -> np.ndarray:
        """Convert photoelectrons to ADU (the inverse of :meth:`to_photons`, without flatfield)."""
        return np.asarray(photons, dtype=np.float64) / self.gain + self.offset

    def as_dict(self) -> dict[str, float]:
        """The scalar parameters, for metadata files (the flatfield is stored separately)."""
        return {
            "offset": self.offset,
            "gain": self.gain,
            "readnoise": self.readnoise,
            "pixel_size_nm": self.pixel_size_nm,
        }

"""Camera model: offset, gain, read noise, pixel size and flatfield.

latentz's likelihood takes each pixel's count as Poisson plus Gaussian read noise, so a Camera
converts ADU to counts with that noise. On a CCD or sCMOS camera they are photoelectrons. An
EMCCD's gain register doubles the variance of each photoelectron (excess noise factor √2 at high
EM gain), so its counts are photoelectrons / 2, Poisson-equivalent ones: :meth:`Camera.emccd`.

The flatfield follows the paper's Results, "A flatfield correction".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from latentz._shared.validate import check_array, check_finite, check_positive

__all__ = ["Camera", "EMCCD_EXCESS_VARIANCE", "poisson_equivalent"]

#: Variance of an EMCCD's output per photoelectron, in units of its mean squared: 2 at EM gains
#: of tens and more (excess noise factor √2; Robbins & Hadwen, IEEE Trans. Electron Devices
#: 2003), where the gain register's multiplication is as noisy as the shot noise itself.
EMCCD_EXCESS_VARIANCE = 2.0
#: The camera values an EMCCD's excess noise rescales.
_HALVED = ("gain", "readnoise")


def poisson_equivalent(given: dict, emccd: bool) -> dict:
    """``given`` camera values with, on an EMCCD (``emccd``), its gain and read noise divided
    by :data:`EMCCD_EXCESS_VARIANCE` where given (not None): Poisson-equivalent counts."""
    return {
        name: value / EMCCD_EXCESS_VARIANCE
        if emccd and name in _HALVED and value is not None
        else value
        for name, value in given.items()
    }


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
    >>> float(cam.to_photons(np.array([[300.0]]))[0, 0])
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

    @classmethod
    def emccd(
        cls,
        *,
        offset: float,
        gain: float,
        readnoise: float = 0.0,
        pixel_size_nm: float = 130.0,
        flatfield: np.ndarray | None = None,
    ) -> Camera:
        """The camera of an EMCCD with its EM gain on, in Poisson-equivalent counts.

        ``gain`` is photoelectrons per ADU (the camera's electrons per ADU over its EM gain) and
        ``readnoise`` the read noise referred to the input (output electrons over the EM gain),
        both as the datasheet gives them. The gain register's excess noise doubles each pixel's
        variance (:data:`EMCCD_EXCESS_VARIANCE`), which a Poisson likelihood of photoelectrons
        would ignore, and every reported σ would be √2 too small. So both are divided by it:
        the counts are photoelectrons / 2, whose variance is their mean, and photon counts that
        latentz reports (``photons``, ``amplitude``, ``background``) are in those units, half
        the photoelectrons. A gain that latentz estimates from a photon-transfer curve is
        Poisson-equivalent already.

        >>> cam = Camera.emccd(offset=100.0, gain=0.1, readnoise=0.5)
        >>> cam.gain, cam.readnoise
        (0.05, 0.25)
        """
        datasheet = {
            "gain": check_positive("gain", gain),
            "readnoise": check_positive("readnoise", readnoise, allow_zero=True),
        }
        return cls(offset=offset, pixel_size_nm=pixel_size_nm, flatfield=flatfield,
                   **poisson_equivalent(datasheet, emccd=True))  # fmt: skip

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

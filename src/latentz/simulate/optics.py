"""Scalar pupil-function optics: the point spread function of a widefield microscope.

The image of a point emitter at defocus ``d`` is the squared modulus of the Fourier transform of the
pupil function

    P(u, v; d) = A(u, v) exp{i 2π/λ [W(u, v) + d n cos θ(u, v)]},

where (u, v) are pupil spatial frequencies (cycles/nm) inside the circle of radius NA/λ, A is the
pupil aperture, W the aberration wavefront (a sum of Zernike polynomials, in nm) and
``n cos θ = sqrt(n² − λ²(u² + v²))`` the exact (non-paraxial) scalar defocus term, with ``n`` the
immersion index. Positive ``d`` moves the emitter along +z relative to the focal plane.

The image is evaluated only on the pixels of a small patch with a matrix Fourier transform (two
complex matrix products per plane), which also places the emitter at any sub-pixel position. The
intensity PSF is band-limited to 2 NA/λ, so its samples on a grid finer than λ/(4 NA) determine it
exactly: pixel integration (a convolution with the pixel box) and the projection of a uniformly
fluorescent sphere are then applied exactly, as products in the Fourier domain of those samples.
This is pixel integration in the limit of infinite oversampling.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.fft

from latentz._shared.validate import check_array, check_int, check_positive
from latentz._shared.zernike import zernike_polar
from latentz.simulate._kernels import mft_power

__all__ = ["Optics"]


def _sphere_transfer(freq: np.ndarray, radius_nm: float) -> np.ndarray:
    """Fourier transform (unit at zero) of the projection of a uniform ball of radius ``radius_nm``
    at spatial frequency ``freq`` (cycles/nm): 3 (sin q − q cos q)/q³ with q = 2π f R."""
    q = 2.0 * np.pi * freq * radius_nm
    out = np.ones_like(q)
    big = q > 1e-3
    qb = q[big]
    out[big] = 3.0 * (np.sin(qb) - qb * np.cos(qb)) / qb**3
    small = ~big
    out[small] = 1.0 - q[small] ** 2 / 10.0
    return out


@dataclass(frozen=True)
class Optics:
    """A widefield microscope: objective, tube lens and camera pixel.

    Parameters
    ----------
    na : float
        Numerical aperture of the objective (0 < na < immersion_index).
    wavelength_nm : float
        Emission wavelength in vacuum, in nm.
    immersion_index : float
        Refractive index of the immersion (and sample) medium; 1.0 for an air objective.
    magnification : float
        Total magnification from sample to camera.
    camera_pixel_um : float
        Physical pixel pitch of the camera chip, in µm. The sample-plane pixel is
        ``camera_pixel_um * 1000 / magnification`` nm.
    pupil_samples : int
        Samples across the pupil diameter (>= 16). The computed PSF repeats with a period of
        ``pupil_samples * λ / (2 NA)`` nm, which must exceed the patches rendered.

    Notes
    -----
    The defaults are the paper's microscope: an air objective of NA 0.55 and 50x magnification onto
    a camera with 6.5 µm pixels (130 nm in the sample), with far-red emission near 680 nm.
    """

    na: float = 0.55
    wavelength_nm: float = 680.0
    immersion_index: float = 1.0
    magnification: float = 50.0
    camera_pixel_um: float = 6.5
    pupil_samples: int = 32

    def __post_init__(self) -> None:
        for name in ("na", "wavelength_nm", "immersion_index", "magnification", "camera_pixel_um"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        object.__setattr__(
            self, "pupil_samples", check_int("pupil_samples", self.pupil_samples, minimum=16)
        )
        if self.na >= self.immersion_index:
            raise ValueError(
                f"Expected `na` to be smaller than `immersion_index` ({self.immersion_index}), "
                f"got {self.na}."
            )

    @property
    def pixel_size_nm(self) -> float:
        """Pixel size in the sample plane, in nm."""
        return self.camera_pixel_um * 1000.0 / self.magnification

    @property
    def gaussian_sigma_nm(self) -> float:
        """Standard deviation of the Gaussian that best matches the in-focus PSF, 0.21 λ/NA."""
        return 0.21 * self.wavelength_nm / self.na

    @property
    def max_ray_slope(self) -> float:
        """tan θ of the marginal ray: the geometric blur radius per nm of defocus."""
        return self.na / math.sqrt(self.immersion_index**2 - self.na**2)

    def as_dict(self) -> dict[str, float]:
        """Parameters for metadata files."""
        return {
            "na": self.na,
            "wavelength_nm": self.wavelength_nm,
            "immersion_index": self.immersion_index,
            "magnification": self.magnification,
            "camera_pixel_um": self.camera_pixel_um,
            "pixel_size_nm": self.pixel_size_nm,
            "pupil_samples": self.pupil_samples,
        }

    @cached_property
    def _pupil(self) -> dict[str, np.ndarray]:
        """Pupil grid: frequencies (cycles/nm), polar coordinates, aperture and n cos θ."""
        m = self.pupil_samples
        cutoff = self.na / self.wavelength_nm
        step = 2.0 * cutoff / m
        freqs = (np.arange(m) - (m - 1) / 2.0) * step
        fu, fv = np.meshgrid(freqs, freqs)  # fu along x (columns), fv along y (rows)
        radius = np.hypot(fu, fv) / cutoff
        # Soft edge: the fraction of each pupil sample that lies inside the unit circle.
        aperture = np.clip((1.0 - radius) * (m / 2.0) + 0.5, 0.0, 1.0)
        inside = aperture > 0
        ncos = np.sqrt(
            np.clip(self.immersion_index**2 - (self.wavelength_nm**2) * (fu**2 + fv**2), 0, None)
        )
        return {
            "freqs": freqs,
            "step": np.float64(step),
            "rho": np.where(inside, np.minimum(radius, 1.0), 0.0),
            "theta": np.arctan2(fv, fu),
            "aperture": aperture,
            "inside": inside,
            "ncos": ncos,
        }

    @cached_property
    def _basis_cache(self) -> dict[tuple[int, ...], np.ndarray]:
        return {}

    def zernike_basis(self, modes: tuple[int, ...]) -> np.ndarray:
        """Zernike polynomials ``modes`` on the pupil grid: (n_modes, m, m), zero outside."""
        modes = tuple(int(j) for j in modes)
        cache = self._basis_cache
        if modes not in cache:
            pupil = self._pupil
            if any(j < 1 for j in modes):
                raise ValueError(f"Expected Noll indices >= 1, got {modes}.")
            table = zernike_polar(
                pupil["rho"].ravel(), pupil["theta"].ravel(), max(modes, default=1)
            )
            basis = table[:, [j - 1 for j in modes]].T.reshape(len(modes), *pupil["rho"].shape)
            cache[modes] = np.where(pupil["inside"][None], basis, 0.0)
        return cache[modes]

    def wavefront_nm(self, zernike_nm: Mapping[int, float]) -> np.ndarray:
        """Aberration wavefront over the pupil grid, in nm, from Noll-indexed Zernike RMS
        coefficients in nm (piston and tilts are allowed but only shift the image)."""
        modes = tuple(int(j) for j in zernike_nm)
        values = np.array([float(zernike_nm[j]) for j in zernike_nm], dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"Expected finite Zernike coefficients, got {dict(zernike_nm)}.")
        return np.tensordot(values, self.zernike_basis(modes), axes=1)

    def focus_shift_per_defocus_nm(self) -> float:
        """Best-focus shift of the emitter per nm of Noll defocus coefficient ``Z4``.

        A wavefront ``c4 Z4`` is balanced, in the least-squares (minimum RMS, Maréchal) sense, by a
        defocus ``d`` whose wavefront is ``d (n cos θ)`` with piston removed:

            d* = −c4 <Z4, n cos θ> / ||n cos θ − <n cos θ>||²

        over the unit pupil. In the paraxial limit n cos θ ≈ n − NA² ρ²/(2n) and this is
        ``d* = 4 √3 n c4 / NA²``. The return value is ``d* / c4``, computed on a fine radial grid.
        """
        rho = (np.arange(20000) + 0.5) / 20000
        weight = rho / rho.sum()  # area weight over the unit disk
        ncos = np.sqrt(self.immersion_index**2 - (self.na * rho) ** 2)
        z4 = math.sqrt(3.0) * (2 * rho**2 - 1)
        centred = ncos - np.sum(weight * ncos)
        return float(-np.sum(weight * z4 * ncos) / np.sum(weight * centred**2))

    def psf(
        self,
        defocus_nm,
        *,
        zernike_nm: Mapping[int, float] | None = None,
        shape: tuple[int, int] = (25, 25),
        center: tuple[float, float] | None = None,
        particle_diameter_nm: float = 0.0,
    ) -> np.ndarray:
        """Pixel-integrated image of one emitter, normalised so that the whole image sums to 1.

        Parameters
        ----------
        defocus_nm : float or array (n_z,)
            Axial position of the emitter relative to the focal plane, in nm.
        zernike_nm : mapping Noll index -> RMS coefficient in nm, optional
            Aberrations at this field position (see :class:`AberrationMap`).
        shape : (rows, columns)
            Patch size in pixels.
        center : (x, y), optional
            Emitter position in patch pixels (x = column); default the patch centre.
        particle_diameter_nm : float
            0 for a point emitter, else the diameter of a uniformly fluorescent sphere, whose
            projection is convolved with the PSF.

        Returns
        -------
        ndarray (n_z, rows, columns)
            Fraction of the emitted photons that reach each pixel. The patch sums to slightly less
            than 1: the far wings of the PSF fall outside it.
        """
        defocus = check_array("defocus_nm", defocus_nm, ndim=(0, 1), dtype_kind="uif")
        defocus = np.atleast_1d(defocus).astype(np.float64)
        if len(shape) != 2:
            raise ValueError(f"Expected `shape` to be (rows, columns), got {shape!r}.")
        rows, cols = (check_int("shape", int(s), minimum=1) for s in shape)
        cx, cy = ((cols - 1) / 2.0, (rows - 1) / 2.0) if center is None else map(float, center)
        centers = np.broadcast_to([cx, cy], (defocus.size, 2))
        wave = self.wavefront_nm(zernike_nm or {})[None]
        return self.render_batch(wave, defocus, centers, (rows, cols), particle_diameter_nm)

    def render_batch(
        self,
        waves_nm: np.ndarray,
        defocus_nm: np.ndarray,
        centers: np.ndarray,
        shape: tuple[int, int],
        particle_diameter_nm: float = 0.0,
    ) -> np.ndarray:
        """Images of ``n`` emitters in ``n`` patches at once (the engine behind :meth:`psf`).

        ``waves_nm`` (n or 1, m, m) are pupil wavefronts from :meth:`wavefront_nm`,
        ``defocus_nm`` (n,) the emitters' defocus and ``centers`` (n, 2) their (x, y) positions in
        patch pixels; all patches have ``shape``. Returns (n, rows, columns).
        """
        defocus = np.asarray(defocus_nm, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(defocus)):
            raise ValueError("Expected `defocus_nm` to be finite.")
        centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(centers)):
            raise ValueError("Expected emitter positions to be finite.")
        rows, cols = shape
        radius = check_positive("particle_diameter_nm", particle_diameter_nm, allow_zero=True) / 2
        pupil = self._pupil
        pixel = self.pixel_size_nm
        # Sampling finer than λ/(4 NA) keeps the band-limited intensity exact; odd so that every
        # pixel centre is a sample.
        over = max(1, math.ceil(4.0 * self.na * pixel / self.wavelength_nm * 1.05))
        over += 1 - over % 2
        sub = pixel / over
        # Sample a little beyond the patch, to a fast FFT length; the extra samples are cropped.
        n_x = scipy.fft.next_fast_len(cols * over + 2 * over, real=True)
        n_y = scipy.fft.next_fast_len(rows * over + 2 * over, real=True)
        grid_x = (np.arange(n_x) - (over - 1) / 2.0) / over * pixel  # nm
        grid_y = (np.arange(n_y) - (over - 1) / 2.0) / over * pixel
        f = pupil["freqs"]
        ax = np.exp(2j * np.pi * np.outer(f, grid_x)).astype(np.complex64)  # (m, cols*over)
        ay = np.exp(2j * np.pi * np.outer(grid_y, f)).astype(np.complex64)  # (rows*over, m)
        # Aberrations, defocus, and (shift theorem) the emitter position, as one pupil phase.
        k = 2.0 * np.pi / self.wavelength_nm
        shift = centers * pixel
        phase = k * (np.asarray(waves_nm) + defocus[:, None, None] * pupil["ncos"][None])
        phase = phase - 2.0 * np.pi * (
            shift[:, 0, None, None] * f[None, None, :] + shift[:, 1, None, None] * f[None, :, None]
        )
        field = (pupil["aperture"][None] * np.exp(1j * phase)).astype(np.complex64)
        intensity = np.empty((field.shape[0], n_y, n_x), dtype=np.float32)
        mft_power(field, ay, ax, intensity)  # |ay @ field @ ax|²
        intensity *= np.float32(pupil["step"] ** 2 / np.sum(pupil["aperture"] ** 2))
        # intensity: probability density per nm²
        # Exact pixel-box integration (and sphere projection) in the Fourier domain.
        fy = np.fft.fftfreq(n_y, d=sub)[:, None]
        fx = np.fft.rfftfreq(n_x, d=sub)[None, :]
        transfer = np.sinc(fy * pixel) * np.sinc(fx * pixel) * pixel**2
        if radius > 0:
            transfer = transfer * _sphere_transfer(np.hypot(fx, fy), radius)
        spectrum = scipy.fft.rfft2(intensity, workers=1) * transfer.astype(np.float32)
        image = scipy.fft.irfft2(spectrum, s=(n_y, n_x), workers=1)
        start = (over - 1) // 2
        return image[:, start : rows * over : over, start : cols * over : over].astype(np.float64)

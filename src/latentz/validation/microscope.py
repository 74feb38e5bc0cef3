"""Optics of the validation microscope: a scalar pupil-function PSF, computed independently.

This module shares no code with :mod:`latentz.simulate` or :mod:`latentz._shared.zernike`, and
takes a
different numerical route, so that agreement between latentz and this microscope is evidence and
not self-consistency:

- the pupil is sampled by a polar quadrature (Gauss–Legendre in the radius, uniform in the
  azimuth), not a Cartesian grid;
- the field in the image is a direct discrete Fourier sum over those pupil nodes, evaluated at
  sub-pixel sample points (``subsamples`` × ``subsamples`` per pixel), and pixel integration is
  the mean over those samples (not an exact Fourier-domain box filter);
- the aberration polynomials are written out below, in terms of the normalised pupil radius ρ
  and azimuth φ, with unit RMS over the pupil.

The amplitude in the image of a point emitter at lateral offset (x, y) and defocus ``a`` (nm) is

    E(x, y) = Σ_k w_k exp{i 2π/λ [W(ρ_k, φ_k) + a sqrt(n² − NA² ρ_k²)]} exp{i 2π (u_k x + v_k y)}

with (u_k, v_k) = ρ_k NA/λ (cos φ_k, sin φ_k) and w_k the quadrature weights of the disk of radius
NA/λ, so that ∫|E|² = π (NA/λ)² for an unaberrated pupil (Parseval) and ``|E|² / (π (NA/λ)²)``
integrates to one photon. At high NA two more factors enter (both optional, both off for the
low-NA microscope of :func:`latentz.validation.make_data`):

- ``apodize``: the aplanatic objective's amplitude factor ``cos(θ)^(-1/2)`` for the emission
  collected at angle θ in the medium (sin θ = NA ρ / n), from the sine condition and energy
  conservation;
- ``vectorial``: the emitter is an isotropic (freely rotating) dipole, and the image is the
  incoherent sum over the dipole along x, y, z and over the x and y polarisations of the
  field in the pupil, each a pupil factor (the dipole's far field projected on the pupil's
  radial and azimuthal unit vectors and brought to the image side):

      E_x = (cos θ cos² φ + sin² φ) μ_x + (cos θ − 1) sin φ cos φ μ_y − sin θ cos φ μ_z
      E_y = (cos θ − 1) sin φ cos φ μ_x + (cos θ sin² φ + cos² φ) μ_y − sin θ sin φ μ_z

Intensities are normalised by the pupil's total power ``Σ_k w_k |P_k|²`` (Parseval), which is
π (NA/λ)² for the plain scalar pupil. A bead is the incoherent sum over its volume: three
axial slices (Gauss quadrature for the sphere's cross-section area, weight 1 − t²), each a uniform
disc of the sphere's radius at that height, convolved with the slice's PSF in the Fourier domain
(the disc's transform is an Airy pattern).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["POLYNOMIALS", "Microscope", "bead_slices"]

#: The aberration polynomials (unit RMS over the unit pupil) of the validation microscope.
POLYNOMIALS = {
    "astig_oblique": lambda r, p: np.sqrt(6) * r**2 * np.sin(2 * p),
    "astig_vertical": lambda r, p: np.sqrt(6) * r**2 * np.cos(2 * p),
    "coma_x": lambda r, p: np.sqrt(8) * (3 * r**3 - 2 * r) * np.cos(p),
    "coma_y": lambda r, p: np.sqrt(8) * (3 * r**3 - 2 * r) * np.sin(p),
    "spherical": lambda r, p: np.sqrt(5) * (6 * r**4 - 6 * r**2 + 1),
}


def bead_slices(diameter_nm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axial offsets (nm), disc radii (nm) and weights (sum 1) of three slices through a uniform
    sphere.

    Gauss quadrature for the weight 1 − t² on [−1, 1] (the cross-section area): nodes 0 and
    ±sqrt(3/7), exact for polynomials in t up to degree 5.
    """
    radius = diameter_nm / 2
    if radius <= 0:
        return np.zeros(1), np.zeros(1), np.ones(1)
    t = np.sqrt(3 / 7) * np.array([-1.0, 0.0, 1.0])
    return radius * t, radius * np.sqrt(1 - t**2), np.array([7 / 30, 8 / 15, 7 / 30])


def _blur_by_disc(intensity: np.ndarray, radius_nm: np.ndarray, step_nm: float) -> np.ndarray:
    """(m, ny, nx) intensity sampled every ``step_nm`` convolved with a uniform disc of radius
    ``radius_nm`` (m,) (or one radius for all), the disc normalised to unit area.

    The disc's transform is 2 J₁(2π f r) / (2π f r) at spatial frequency f. The intensity is
    band-limited to 2 NA/λ; where the samples resolve it (``step_nm`` ≤ λ / (4 NA)), multiplying
    its discrete transform by that factor convolves the continuous intensity, up to the light
    that wraps around the grid's edges.
    """
    from scipy.special import j1

    ny, nx = intensity.shape[-2:]
    fy, fx = np.fft.fftfreq(ny, step_nm), np.fft.rfftfreq(nx, step_nm)
    f = np.hypot(fy[:, None], fx[None, :])
    arg = 2 * np.pi * f[None] * np.broadcast_to(radius_nm, intensity.shape[:1])[:, None, None]
    safe = np.where(arg > 0, arg, 1.0)
    factor = np.where(arg > 0, 2 * j1(safe) / safe, 1.0)
    return np.fft.irfft2(np.fft.rfft2(intensity) * factor, s=(ny, nx))


@dataclass(frozen=True)
class Microscope:
    """A widefield microscope with a circular pupil; lengths in nm.

    Attributes
    ----------
    na, wavelength_nm, pixel_size_nm, n_medium : float
        Numerical aperture, emission wavelength, sample-plane pixel size, immersion index.
    radial_nodes, azimuth_nodes : int
        Pupil quadrature: Gauss–Legendre nodes in ρ, uniform nodes in φ.
    subsamples : int
        Sample points per pixel along each axis for pixel integration.
    apodize : bool
        Apply the aplanatic amplitude factor cos(θ)^(-1/2) (module notes).
    vectorial : bool
        Image an isotropic dipole with the vectorial pupil factors (module notes).
    """

    na: float = 0.55
    wavelength_nm: float = 640.0
    pixel_size_nm: float = 130.0
    n_medium: float = 1.0
    radial_nodes: int = 20
    azimuth_nodes: int = 40
    subsamples: int = 3
    apodize: bool = False
    vectorial: bool = False

    @cached_property
    def _nodes(self) -> dict[str, np.ndarray]:
        t, wt = np.polynomial.legendre.leggauss(self.radial_nodes)
        rho, w_rho = (t + 1) / 2, wt / 2  # on [0, 1]
        phi = 2 * np.pi * (np.arange(self.azimuth_nodes) + 0.5) / self.azimuth_nodes
        rr, pp = (a.ravel() for a in np.meshgrid(rho, phi, indexing="ij"))
        cutoff = self.na / self.wavelength_nm
        weight = np.repeat(w_rho * rho, self.azimuth_nodes) * (2 * np.pi / self.azimuth_nodes)
        return {
            "rho": rr,
            "phi": pp,
            "u": rr * cutoff * np.cos(pp),
            "v": rr * cutoff * np.sin(pp),
            "weight": weight * cutoff**2,
            "axial": np.sqrt(self.n_medium**2 - (self.na * rr) ** 2),
        }

    @cached_property
    def _factors(self) -> np.ndarray:
        """(c, K) real pupil factors of the c incoherent components (module notes)."""
        nodes = self._nodes
        cos_t = nodes["axial"] / self.n_medium
        apodization = cos_t**-0.5 if self.apodize else np.ones_like(cos_t)
        if not self.vectorial:
            return apodization[None, :]
        sin_t = self.na * nodes["rho"] / self.n_medium
        cp, sp = np.cos(nodes["phi"]), np.sin(nodes["phi"])
        mixed = (cos_t - 1) * sp * cp
        factors = [cos_t * cp**2 + sp**2, mixed, -sin_t * cp,  # E_x for mu_x, mu_y, mu_z
                   mixed, cos_t * sp**2 + cp**2, -sin_t * sp]  # E_y  # fmt: skip
        return np.array(factors) * apodization / np.sqrt(3.0)

    @cached_property
    def pupil_power(self) -> float:
        """``Σ_c Σ_k w_k |P_ck|²``, the integral of the image intensity over the plane (nm⁻²)."""
        return float(np.sum(self._nodes["weight"] * self._factors**2))

    @property
    def pupil_area(self) -> float:
        """π (NA/λ)², the integral of |E|² for a unit pupil (nm⁻²)."""
        return np.pi * (self.na / self.wavelength_nm) ** 2

    def wavefront_nm(self, coefficients_nm: dict[str, float] | np.ndarray) -> np.ndarray:
        """Aberration wavefront (nm) at the pupil nodes from {mode: nm RMS}, or an array in the
        order of :data:`POLYNOMIALS`."""
        if not isinstance(coefficients_nm, dict):
            coefficients_nm = dict(zip(POLYNOMIALS, np.asarray(coefficients_nm), strict=True))
        nodes = self._nodes
        wave = np.zeros_like(nodes["rho"])
        for mode, c in coefficients_nm.items():
            wave = wave + c * POLYNOMIALS[mode](nodes["rho"], nodes["phi"])
        return wave

    def amplitude(
        self,
        x_nm: np.ndarray,
        y_nm: np.ndarray,
        wavefront_nm: np.ndarray,
        defocus_nm: np.ndarray,
        *,
        factor: np.ndarray | None = None,
    ) -> np.ndarray:
        """Complex amplitude E on the grid ``y_nm × x_nm`` for each defocus: (m, ny, nx), with the
        pupil multiplied by ``factor`` (K,) (default none).

        ``|E|² / pupil_area`` is the intensity per nm² of one photon for the plain scalar pupil.
        """
        nodes = self._nodes
        k = 2 * np.pi / self.wavelength_nm
        defocus = np.atleast_1d(np.asarray(defocus_nm, dtype=np.float64))
        phase = k * (wavefront_nm[None, :] + defocus[:, None] * nodes["axial"][None, :])
        weight = nodes["weight"] if factor is None else nodes["weight"] * factor
        pupil = (weight * np.exp(1j * phase)).astype(np.complex64)  # (m, K)
        along_y = np.exp(2j * np.pi * np.outer(y_nm, nodes["v"])).astype(np.complex64)
        along_x = np.exp(2j * np.pi * np.outer(nodes["u"], x_nm)).astype(np.complex64)
        left = (pupil[:, None, :] * along_y[None]).reshape(-1, nodes["u"].size)
        return (left @ along_x).reshape(defocus.size, len(y_nm), len(x_nm))

    def intensity(
        self, x_nm: np.ndarray, y_nm: np.ndarray, wavefront_nm: np.ndarray, defocus_nm: np.ndarray
    ) -> np.ndarray:
        """Intensity per nm² of one photon on the grid ``y_nm × x_nm``: (m, ny, nx), the
        incoherent sum over the pupil's components (module notes)."""
        total = 0.0
        for factor in self._factors:
            field = self.amplitude(x_nm, y_nm, wavefront_nm, defocus_nm, factor=factor)
            total = total + (field.real**2 + field.imag**2)
        return total / self.pupil_power

    def pixel_image(
        self,
        dx_px: float,
        dy_px: float,
        wavefront_nm: np.ndarray,
        defocus_nm: np.ndarray,
        size: int,
        *,
        weights: np.ndarray | None = None,
        disc_radius_nm: np.ndarray | None = None,
    ) -> np.ndarray:
        """Expected fraction of the photons in each pixel of a ``size`` × ``size`` patch: (m, size,
        size), or one image (size, size) summed with ``weights`` over the m defocus values.

        The emitter sits ``(dx_px, dy_px)`` from the centre of the patch's central pixel. With
        ``disc_radius_nm`` (m,), the emitter at each defocus is a uniform disc of that radius
        (a slice through a bead), not a point.
        """
        q = self.subsamples
        half = size // 2
        step_nm = self.pixel_size_nm / q
        radius = np.zeros(1) if disc_radius_nm is None else np.asarray(disc_radius_nm, float)
        pad = int(np.ceil(radius.max() / step_nm)) + 2 if radius.max() > 0 else 0
        offsets = (np.arange(-pad, size * q + pad) + 0.5) / q - 0.5 - half  # sample points, px
        x_nm = (offsets - dx_px) * self.pixel_size_nm
        y_nm = (offsets - dy_px) * self.pixel_size_nm
        intensity = self.intensity(x_nm, y_nm, wavefront_nm, defocus_nm)
        if pad:
            intensity = _blur_by_disc(intensity, radius, step_nm)[:, pad:-pad, pad:-pad]
        pixels = intensity.reshape(-1, size, q, size, q).mean(axis=(2, 4))
        pixels = pixels * self.pixel_size_nm**2
        if weights is None:
            return pixels
        return np.tensordot(np.asarray(weights, dtype=np.float64), pixels, axes=(0, 0))

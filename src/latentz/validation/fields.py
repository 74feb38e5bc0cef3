"""Aberration fields of the validation microscope: polynomial, smooth random, or with defects.

Each aberration coefficient (nm RMS of its pupil polynomial, see
:mod:`latentz.validation.microscope`) is a constant plus a field of zero mean across the field of
view, in one of three forms (:data:`FORMS`):

- ``"polynomial"``: a random polynomial of field position up to the third degree, the kind a few
  Zernike terms of field position describe (:meth:`AberrationFields.polynomial`);
- ``"smooth"``: a smooth random field, white noise smoothed by a Gaussian whose width is a
  fraction of the field, scaled to a chosen standard deviation (:meth:`AberrationFields.random`
  with no defect);
- ``"defects"``: the smooth field plus local defects, Gaussian bumps a few percent of the field
  wide (:meth:`AberrationFields.random`, one defect by default). The focal
surface is curved (a paraboloid, ``curvature_nm`` higher at the corners than at the centre) and
the calibration substrate is tilted by ``tilt_mrad``. Only the first form is a polynomial of the
kind a few Zernike terms of field position describe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

__all__ = ["FORMS", "MODES", "AberrationFields"]

#: Aberration modes of the validation microscope, in the order of ``AberrationFields.maps``.
MODES = ("astig_oblique", "astig_vertical", "coma_x", "coma_y", "spherical")
#: Forms of the aberrations' variation across the field (module notes).
FORMS = ("polynomial", "smooth", "defects")

# Default constant part and field standard deviation of each mode, nm RMS.
_MEAN_NM = {"astig_oblique": 65.0, "astig_vertical": 0.0, "coma_x": 0.0, "coma_y": 0.0,
            "spherical": 5.0}  # fmt: skip
_STD_NM = {"astig_oblique": 6.0, "astig_vertical": 6.0, "coma_x": 8.0, "coma_y": 8.0,
           "spherical": 3.0}  # fmt: skip


@dataclass(frozen=True, eq=False)
class AberrationFields:
    """Aberration coefficients and focal-surface height over a ``(H, W)`` pixel field.

    Attributes
    ----------
    maps : ndarray (n_modes, H, W)
        Coefficient of each of :data:`MODES` at every pixel centre, nm RMS.
    curvature_nm : float
        Height of the focal surface at the field's corners above its centre, nm.
    tilt_mrad : float
        Tilt of the calibration substrate, mrad, rising along ``tilt_direction_rad``.
    tilt_direction_rad : float
        Direction of steepest ascent of the substrate in the (x, y) plane.
    pixel_size_nm : float
        Sample-plane pixel size, nm.
    """

    maps: np.ndarray
    curvature_nm: float
    tilt_mrad: float
    tilt_direction_rad: float
    pixel_size_nm: float

    @classmethod
    def random(
        cls,
        field_shape: tuple[int, int],
        *,
        seed: int = 0,
        correlation_fraction: float = 0.25,
        defect_fraction: float = 0.05,
        defect_nm: float = 15.0,
        curvature_nm: float = 150.0,
        tilt_mrad: float = 2.0,
        pixel_size_nm: float = 130.0,
        scale: float = 1.0,
        mean_nm: dict[str, float] | None = None,
        std_nm: dict[str, float] | None = None,
        n_defects: int = 1,
    ) -> AberrationFields:
        """Smooth random fields with ``n_defects`` local defects.

        ``correlation_fraction`` is the Gaussian smoothing width as a fraction of the longer field
        side, ``defect_fraction`` the defects' width likewise; ``defect_nm`` their peak, applied
        to every mode with a random sign and a weight in [0.5, 1]. ``scale`` multiplies the random
        and defect parts (0 gives a field-independent microscope). ``mean_nm`` and ``std_nm``
        (nm RMS per mode of :data:`MODES`) replace the default constant parts and field standard
        deviations.
        """
        rng = np.random.default_rng(seed)
        mean, std = {**_MEAN_NM, **(mean_nm or {})}, {**_STD_NM, **(std_nm or {})}
        h, w = field_shape
        side = max(h, w)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        bumps = []
        for _ in range(n_defects):
            centre = rng.uniform(0.2, 0.8, 2) * np.array([w, h])
            width = defect_fraction * side
            bumps.append(np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * width**2)))
        maps = []
        for mode in MODES:
            noise = gaussian_filter(rng.normal(size=(h, w)), correlation_fraction * side,
                                    mode="reflect")  # fmt: skip
            noise = (noise - noise.mean()) / noise.std()
            defect = sum(defect_nm * rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * bump
                         for bump in bumps)  # fmt: skip
            maps.append(mean[mode] + scale * (std[mode] * noise + defect))
        return cls._assemble(maps, rng, curvature_nm, tilt_mrad, pixel_size_nm)

    @classmethod
    def polynomial(
        cls,
        field_shape: tuple[int, int],
        *,
        seed: int = 0,
        degree: int = 3,
        curvature_nm: float = 150.0,
        tilt_mrad: float = 2.0,
        pixel_size_nm: float = 130.0,
        mean_nm: dict[str, float] | None = None,
        std_nm: dict[str, float] | None = None,
    ) -> AberrationFields:
        """Each mode a constant plus a random polynomial of field position of total degree
        ``degree`` (normal coefficients of the monomials in coordinates scaled to [−1, 1]),
        centred and scaled to the mode's standard deviation over the field."""
        rng = np.random.default_rng(seed)
        mean, std = {**_MEAN_NM, **(mean_nm or {})}, {**_STD_NM, **(std_nm or {})}
        h, w = field_shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        u, v = 2 * xx / max(w - 1, 1) - 1, 2 * yy / max(h - 1, 1) - 1
        terms = [u**i * v**j for i in range(degree + 1) for j in range(degree + 1 - i) if i + j]
        maps = []
        for mode in MODES:
            field = sum(rng.normal() * t for t in terms)
            field = (field - field.mean()) / field.std()
            maps.append(mean[mode] + std[mode] * field)
        return cls._assemble(maps, rng, curvature_nm, tilt_mrad, pixel_size_nm)

    @classmethod
    def _assemble(
        cls,
        maps: list[np.ndarray],
        rng: np.random.Generator,
        curvature_nm: float,
        tilt_mrad: float,
        pixel_size_nm: float,
    ) -> AberrationFields:
        """The fields of ``maps`` (one per mode of :data:`MODES`, nm RMS), the tilt's direction
        drawn from ``rng`` after them."""
        return cls(
            np.array(maps),
            float(curvature_nm),
            float(tilt_mrad),
            float(rng.uniform(0, 2 * np.pi)),
            float(pixel_size_nm),
        )

    @property
    def field_shape(self) -> tuple[int, int]:
        """``(H, W)`` in pixels."""
        return self.maps.shape[1], self.maps.shape[2]

    def coefficients(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """(n, n_modes) coefficients (nm RMS) at field positions (pixels), bilinear between
        pixel centres."""
        coords = np.stack([np.asarray(y_px, float), np.asarray(x_px, float)])
        return np.stack(
            [map_coordinates(m, coords, order=1, mode="nearest") for m in self.maps], axis=1
        )

    def focal_surface_nm(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Height (nm) of the surface of paraxial focus above its centre value."""
        h, w = self.field_shape
        cx, cy = (w - 1) / 2, (h - 1) / 2
        r2 = (np.asarray(x_px) - cx) ** 2 + (np.asarray(y_px) - cy) ** 2
        return self.curvature_nm * r2 / (cx**2 + cy**2)

    def substrate_nm(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Height (nm) of the tilted calibration substrate, zero at the field centre."""
        h, w = self.field_shape
        along = (np.asarray(x_px) - (w - 1) / 2) * np.cos(self.tilt_direction_rad)
        along = along + (np.asarray(y_px) - (h - 1) / 2) * np.sin(self.tilt_direction_rad)
        return self.tilt_mrad * 1e-3 * along * self.pixel_size_nm

"""Tilt of the calibration substrate and the field curvature that remains (Supp. Figs. 3, 8).

The surface of best focus z_f(x, y) of the calibration particles is fitted by a plane
``z = c0 + cx x + cy y`` (x, y, z in nm; uniform least squares). Subtracting the plane levels the
substrate analytically (paper Methods, "Tilt correction"); what remains is the field curvature
(Supp. Fig. 3). The substrate normal ``(−cx, −cy, 1)`` is tilted from the optical axis by the
nutation ``β = atan(√(cx² + cy²))`` toward the azimuth ``atan2(−cy, −cx)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from latentz._shared.validate import check_array

__all__ = ["TiltPlane"]


@dataclass(frozen=True)
class TiltPlane:
    """The plane ``z = c0 + cx x + cy y`` of best focus (x, y, z in nm).

    Examples
    --------
    >>> x, y = np.meshgrid(np.arange(0.0, 1e5, 1e4), np.arange(0.0, 1e5, 1e4))
    >>> z = np.tan(2e-3) * x.ravel() + 40.0  # 2 mrad along x
    >>> plane = TiltPlane.from_estimate(x.ravel(), y.ravel(), z)
    >>> round(plane.nutation_mrad, 6)
    2.0
    """

    c0: float
    cx: float
    cy: float

    @classmethod
    def from_estimate(cls, x_nm: Any, y_nm: Any, z_nm: Any, *, mask: Any = None) -> TiltPlane:
        """Least-squares plane through the points (``mask`` selects those to use)."""
        x = check_array("x_nm", x_nm, ndim=1).astype(np.float64)
        y = check_array("y_nm", y_nm, ndim=1).astype(np.float64)
        z = check_array("z_nm", z_nm, ndim=1).astype(np.float64)
        if not x.shape == y.shape == z.shape:
            raise ValueError(
                f"Expected `x_nm`, `y_nm`, `z_nm` of one length, got {x.size}, {y.size}, {z.size}."
            )
        use = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        if mask is not None:
            use &= np.asarray(mask, dtype=bool)
        if use.sum() < 3:
            raise ValueError(
                f"A tilt plane needs at least 3 particles in focus, got {int(use.sum())}."
            )
        design = np.stack([np.ones(use.sum()), x[use], y[use]], axis=1)
        if np.linalg.matrix_rank(design) < 3:
            raise ValueError("The particles are collinear: the tilt plane is undetermined.")
        coef = np.linalg.lstsq(design, z[use], rcond=None)[0]
        return cls(*(float(c) for c in coef))

    @classmethod
    def flat(cls, z0: float = 0.0) -> TiltPlane:
        """A plane normal to the optical axis at ``z0`` (no tilt correction)."""
        return cls(float(z0), 0.0, 0.0)

    def __call__(self, x_nm: Any, y_nm: Any) -> np.ndarray:
        """z of the plane at (x, y), nm."""
        return self.c0 + self.cx * np.asarray(x_nm, float) + self.cy * np.asarray(y_nm, float)

    def residuals(self, x_nm: Any, y_nm: Any, z_nm: Any) -> np.ndarray:
        """``z − plane(x, y)``: the field curvature map when z is z_f, nm."""
        return np.asarray(z_nm, dtype=np.float64) - self(x_nm, y_nm)

    @property
    def nutation_mrad(self) -> float:
        """Angle between the substrate normal and the optical axis, mrad."""
        return float(1e3 * np.arctan(np.hypot(self.cx, self.cy)))

    @property
    def azimuth_rad(self) -> float:
        """Direction (from +x toward +y) in which the substrate normal leans, rad."""
        return float(np.arctan2(-self.cy, -self.cx))

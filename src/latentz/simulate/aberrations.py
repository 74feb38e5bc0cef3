"""Field-dependent aberrations: Zernike coefficients that vary smoothly across the field.

Each aberration is a Noll-indexed Zernike polynomial of the pupil with an RMS coefficient in nm of
wavefront. Across the field, every coefficient is a cubic polynomial of the normalised field
coordinates

    u = (x − (W − 1)/2) / (W/2),   v = (y − (H − 1)/2) / (H/2),

so u, v run from −1 to 1 over a field of H × W pixels (x = column, y = row).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from latentz._shared.validate import check_array, check_int, check_positive

__all__ = ["AberrationMap", "MONOMIALS", "MODE_NAMES"]

#: Powers (i, j) of the field monomials u^i v^j, in the column order of ``coefficients_nm``.
MONOMIALS: tuple[tuple[int, int], ...] = (
    (0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3),
)  # fmt: skip

MODE_NAMES = {
    4: "defocus",
    5: "oblique astigmatism",
    6: "vertical astigmatism",
    7: "vertical coma",
    8: "horizontal coma",
    9: "vertical trefoil",
    10: "oblique trefoil",
    11: "primary spherical",
}

# The paper-like default, in nm RMS: (Noll index, {monomial: coefficient}).
_DEFAULT_TERMS: dict[int, dict[tuple[int, int], float]] = {
    # Field curvature: best focus moves by ~21 nm per nm of Z4 at NA 0.55 in air, so 22 nm at
    # the field edge (u² + v² = 1) is ~0.46 µm, and ~0.93 µm at the corners.
    4: {(2, 0): 22.0, (0, 2): 22.0},
    # Dominant oblique astigmatism (ellipse axes at ±π/4, so ρ carries z), plus the off-axis
    # (Seidel) astigmatism that grows with field height squared.
    5: {(0, 0): 45.0, (1, 1): 12.0},
    6: {(0, 0): 3.0, (2, 0): 6.0, (0, 2): -6.0},
    # Coma: a small misalignment plus the off-axis part linear in field height.
    7: {(0, 0): 3.0, (0, 1): 10.0},
    8: {(0, 0): -2.0, (1, 0): 10.0},
    # Primary spherical aberration, slightly stronger at the edge.
    11: {(0, 0): 12.0, (2, 0): 3.0, (0, 2): 3.0},
}
_DEFAULT_MODES = (4, 5, 6, 7, 8, 9, 10, 11)


def _monomials(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.stack([u**i * v**j for i, j in MONOMIALS], axis=-1)


@dataclass(frozen=True, eq=False)
class AberrationMap:
    """Zernike aberration coefficients as smooth (cubic) functions of field position.

    Parameters
    ----------
    modes : tuple of int
        Noll indices of the aberrations (see ``MODE_NAMES``).
    coefficients_nm : ndarray (n_modes, 10)
        Coefficients of the field monomials ``MONOMIALS`` for each mode, in nm RMS of wavefront.
    field_shape : (rows, columns)
        The full camera field over which u and v run from −1 to 1, in pixels.

    Examples
    --------
    >>> ab = AberrationMap.constant({5: 40.0})
    >>> ab.zernike_at(1023.5, 1023.5)
    {5: 40.0}
    """

    modes: tuple[int, ...]
    coefficients_nm: np.ndarray
    field_shape: tuple[int, int] = (2048, 2048)

    def __post_init__(self) -> None:
        modes = tuple(check_int("modes", int(m), minimum=1) for m in self.modes)
        if len(set(modes)) != len(modes):
            raise ValueError(f"Expected `modes` to be distinct Noll indices, got {modes}.")
        coef = check_array(
            "coefficients_nm", self.coefficients_nm, ndim=2, dtype_kind="uif", allow_empty=True
        ).astype(np.float64)
        if coef.shape != (len(modes), len(MONOMIALS)):
            raise ValueError(
                f"Expected `coefficients_nm` to have shape {(len(modes), len(MONOMIALS))}, "
                f"got {coef.shape}."
            )
        if not np.all(np.isfinite(coef)):
            raise ValueError("Expected `coefficients_nm` to be finite.")
        if len(self.field_shape) != 2:
            raise ValueError(
                f"Expected `field_shape` to be (rows, columns), got {self.field_shape}."
            )
        shape = tuple(check_int("field_shape", int(s), minimum=1) for s in self.field_shape)
        coef.setflags(write=False)
        object.__setattr__(self, "modes", modes)
        object.__setattr__(self, "coefficients_nm", coef)
        object.__setattr__(self, "field_shape", shape)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, AberrationMap):
            return NotImplemented
        return (
            self.modes == other.modes
            and self.field_shape == other.field_shape
            and np.array_equal(self.coefficients_nm, other.coefficients_nm)
        )

    __hash__ = None  # type: ignore[assignment]

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def constant(
        cls, zernike_nm: Mapping[int, float], *, field_shape: tuple[int, int] = (2048, 2048)
    ) -> AberrationMap:
        """The same aberrations everywhere: ``{noll_index: nm RMS}``."""
        modes = tuple(int(j) for j in zernike_nm)
        coef = np.zeros((len(modes), len(MONOMIALS)))
        coef[:, 0] = [float(zernike_nm[j]) for j in zernike_nm]
        return cls(modes, coef, field_shape)

    @classmethod
    def from_terms(
        cls,
        terms: Mapping[int, Mapping[tuple[int, int], float]],
        *,
        field_shape: tuple[int, int] = (2048, 2048),
    ) -> AberrationMap:
        """From ``{noll_index: {(i, j): nm}}``, the coefficient of u^i v^j for each mode."""
        modes = tuple(int(j) for j in terms)
        coef = np.zeros((len(modes), len(MONOMIALS)))
        for row, j in enumerate(terms):
            for power, value in terms[j].items():
                if tuple(power) not in MONOMIALS:
                    raise ValueError(
                        f"Expected field monomial powers among {MONOMIALS}, got {power!r}."
                    )
                coef[row, MONOMIALS.index(tuple(power))] = float(value)
        return cls(modes, coef, field_shape)

    @classmethod
    def default(
        cls,
        *,
        seed: int | None = 0,
        random_nm: float = 2.0,
        field_shape: tuple[int, int] = (2048, 2048),
    ) -> AberrationMap:
        """Aberrations like the paper's microscope (NA 0.55 air objective, 260 µm field).

        In nm RMS of wavefront (u, v: normalised field coordinates, r² = u² + v²):

        - defocus Z4 = 22 r² (field curvature: best focus ~0.46 µm deeper at the edge and
          ~0.93 µm at the corners than at the centre);
        - oblique astigmatism Z5 = 45 + 12 uv (dominant, so ρ changes sign through focus and is
          monotonic over about ±2–3 µm for 1 µm particles), vertical astigmatism
          Z6 = 3 + 6 (u² − v²);
        - coma Z7 = 3 + 10 v, Z8 = −2 + 10 u (apparent lateral motion of tens of nm over ±2 µm);
        - spherical Z11 = 12 + 3 r²;

        plus, when ``random_nm > 0``, a smooth random part drawn with ``seed``: every monomial
        coefficient of Z4–Z11 gets a normal deviate of standard deviation ``random_nm`` (halved
        for the cubic monomials).
        """
        random_nm = check_positive("random_nm", random_nm, allow_zero=True)
        base = cls.from_terms(
            {j: _DEFAULT_TERMS.get(j, {}) for j in _DEFAULT_MODES}, field_shape=field_shape
        )
        if random_nm == 0:
            return base
        rng = np.random.default_rng(seed)
        scale = np.array([1.0 if i + j < 3 else 0.5 for i, j in MONOMIALS]) * random_nm
        noise = rng.normal(size=base.coefficients_nm.shape) * scale
        return cls(base.modes, base.coefficients_nm + noise, base.field_shape)

    @classmethod
    def none(cls, *, field_shape: tuple[int, int] = (2048, 2048)) -> AberrationMap:
        """A perfect (diffraction-limited) microscope."""
        return cls.constant({}, field_shape=field_shape)

    # -- evaluation ---------------------------------------------------------------------------
    def field_uv(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Normalised field coordinates (u, v) of full-field pixel positions (x, y)."""
        rows, cols = self.field_shape
        u = (np.asarray(x, dtype=np.float64) - (cols - 1) / 2.0) / (cols / 2.0)
        v = (np.asarray(y, dtype=np.float64) - (rows - 1) / 2.0) / (rows / 2.0)
        return u, v

    def at(self, x: Any, y: Any) -> np.ndarray:
        """Coefficients (nm RMS) at full-field pixel positions: array (..., n_modes)."""
        u, v = self.field_uv(x, y)
        return _monomials(u, v) @ self.coefficients_nm.T

    def zernike_at(self, x: float, y: float) -> dict[int, float]:
        """``{noll_index: nm}`` at one full-field pixel position."""
        values = self.at(float(x), float(y))
        return {j: float(c) for j, c in zip(self.modes, values, strict=True)}

    # -- persistence --------------------------------------------------------------------------
    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready description that :meth:`from_dict` restores exactly."""
        return {
            "units": "nm RMS wavefront (Noll-normalised Zernike)",
            "field_coordinates": "u = (x - (W-1)/2)/(W/2), v = (y - (H-1)/2)/(H/2)",
            "field_shape": list(self.field_shape),
            "monomials_uv_powers": [list(p) for p in MONOMIALS],
            "modes": {
                str(j): {"name": MODE_NAMES.get(j, f"Z{j}"), "coefficients_nm": row.tolist()}
                for j, row in zip(self.modes, self.coefficients_nm, strict=True)
            },
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AberrationMap:
        """Inverse of :meth:`as_dict`."""
        modes = tuple(int(j) for j in data["modes"])
        coef = np.array(
            [data["modes"][str(j)]["coefficients_nm"] for j in modes], dtype=np.float64
        ).reshape(len(modes), len(MONOMIALS))
        return cls(modes, coef, tuple(data["field_shape"]))

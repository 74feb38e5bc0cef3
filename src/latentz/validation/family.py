"""A random family of validation microscopes: every setting drawn, truth from geometry.

:func:`draw_microscope` draws one microscope and its sample from a seed (:class:`Draw`):

- immersion (air n = 1, water 1.333, oil 1.518) and NA over 0.4–1.49 within what the medium
  allows; above NA 0.9 an isotropic-dipole vectorial PSF, below a scalar one, both with the
  aplanatic apodisation (:class:`~latentz.validation.microscope.Microscope`);
- emission wavelength 500–700 nm, sample-plane pixel 65–160 nm;
- astigmatism from none to cylindrical-lens strength (focal lines up to 1 µm apart), at a
  random angle; spherical aberration and coma; aberration fields of one of the three
  :data:`~latentz.validation.fields.FORMS` with their own strengths; substrate tilt
  (0–3 mrad) and focal-surface curvature (0–300 nm, either sign);
- calibration particles from points to 200 nm beads, 5·10⁴–5·10⁵ photons, on 1–20 photons of
  background per pixel; the stack through ±(2–4) depths of field λ n / NA² (0.8–3 µm) in
  steps of 4–12 % of it (20–100 nm); the particles' density (the side of each stack's grid);
- test emitters at their own places (never within 3 px of a calibration particle), 10^2.7–10^3.5
  photons at the dimmest and ten times that at the brightest, within 2/3 of the stack's range.

:func:`family_data` images a draw at one of :data:`FAMILY_SIZES`.
"""

from __future__ import annotations

import hashlib
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from latentz._shared.atomic import write_bytes_atomic
from latentz.camera import Camera
from latentz.validation.datasets import ValidationData, simulate_study
from latentz.validation.fields import FORMS, MODES, AberrationFields
from latentz.validation.microscope import Microscope

__all__ = ["FAMILY_SIZES", "MEDIA", "Draw", "draw_microscope", "family_data"]

#: Refractive index and NA range of each immersion.
MEDIA = {"air": (1.0, 0.4, 0.95), "water": (1.333, 0.8, 1.27), "oil": (1.518, 1.1, 1.49)}

#: Sizes of a family member: field side (px), stacks, the range of each stack's grid side, test
#: emitters and frames, the rendered patch (px), and the bounds (nm) the drawn stack half-range
#: and step are held to (``ci``: short stacks for a family that runs in CI).
FAMILY_SIZES = {
    "full": {"field_px": 256, "n_stacks": 2, "grid": (7, 9), "n_test": 60, "n_frames": 10,
             "patch_px": 31, "z_half_nm": (800.0, 3000.0), "z_step_nm": (20.0, 100.0)},
    "small": {"field_px": 128, "n_stacks": 2, "grid": (3, 5), "n_test": 16, "n_frames": 6,
              "patch_px": 27, "z_half_nm": (800.0, 3000.0), "z_step_nm": (20.0, 100.0)},
    "tiny": {"field_px": 96, "n_stacks": 2, "grid": (3, 3), "n_test": 9, "n_frames": 5,
             "patch_px": 23, "z_half_nm": (800.0, 3000.0), "z_step_nm": (20.0, 100.0)},
    "ci": {"field_px": 72, "n_stacks": 2, "grid": (3, 3), "n_test": 6, "n_frames": 4,
           "patch_px": 19, "z_half_nm": (600.0, 1000.0), "z_step_nm": (60.0, 100.0)},
}  # fmt: skip

VECTORIAL_NA = 0.9
# the modules whose code images a draw: a render kept by `family_data` is reused only for the
# same draw and size while their source is unchanged
RENDER_MODULES = ("datasets", "family", "fields", "microscope")


@dataclass(frozen=True)
class Draw:
    """One random microscope and sample (lengths in nm; see the module notes)."""

    seed: int
    size: str
    medium: str
    na: float
    wavelength_nm: float
    pixel_size_nm: float
    form: str
    mean_nm: dict[str, float]
    std_nm: dict[str, float]
    curvature_nm: float
    tilt_mrad: float
    bead_nm: float
    photons: float
    background: float
    test_photons: tuple[float, float]
    z_half_nm: float
    z_step_nm: float
    grid_fraction: float

    @property
    def n_medium(self) -> float:
        return MEDIA[self.medium][0]

    @property
    def astigmatism_nm(self) -> float:
        """RMS of the mean astigmatism (both orientations), nm."""
        return float(np.hypot(self.mean_nm["astig_oblique"], self.mean_nm["astig_vertical"]))

    def microscope(self, patch_px: int) -> Microscope:
        """The optics, with a pupil quadrature fine enough for a ``patch_px`` patch through
        the stack's range (:func:`quadrature_nodes`)."""
        radial, azimuth = quadrature_nodes(self, patch_px)
        return Microscope(na=self.na, wavelength_nm=self.wavelength_nm,
                          pixel_size_nm=self.pixel_size_nm, n_medium=self.n_medium,
                          radial_nodes=radial, azimuth_nodes=azimuth, apodize=True,
                          vectorial=self.na > VECTORIAL_NA)  # fmt: skip

    def fields(self, field_px: int) -> AberrationFields:
        """The aberration fields over a ``field_px`` square field."""
        common = {"seed": self.seed, "curvature_nm": self.curvature_nm,
                  "tilt_mrad": self.tilt_mrad, "pixel_size_nm": self.pixel_size_nm,
                  "mean_nm": self.mean_nm, "std_nm": self.std_nm}  # fmt: skip
        shape = (field_px, field_px)
        if self.form == "polynomial":
            return AberrationFields.polynomial(shape, **common)
        return AberrationFields.random(shape, n_defects=2 if self.form == "defects" else 0,
                                       **common)  # fmt: skip


def quadrature_nodes(draw: Draw, patch_px: int) -> tuple[int, int]:
    """Radial and azimuthal pupil nodes for the draw: enough for the phase across the pupil
    (defocus at the stack's end plus three times the aberrations' RMS) and for the patch's
    corner (its lateral phase ramp), with a margin; checked by the convergence test."""
    n, na, lam = draw.n_medium, draw.na, draw.wavelength_nm
    defocus = (draw.z_half_nm + 0.5 * draw.bead_nm) * (n - np.sqrt(n**2 - na**2)) / lam
    wave = 3 * sum(abs(v) for v in draw.mean_nm.values()) / lam
    corner = na / lam * patch_px / np.sqrt(2) * draw.pixel_size_nm  # cycles across the pupil
    radial = int(np.ceil(10 + 0.9 * (defocus + wave + corner)))
    azimuth = int(np.ceil(16 + 1.5 * np.pi * (corner + wave)))
    return radial, azimuth


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def draw_microscope(seed: int, size: str = "full") -> Draw:
    """Draw one microscope and sample (module notes) from ``seed``, to be imaged at ``size``
    (:data:`FAMILY_SIZES`; its stack bounds clip the drawn half-range and step)."""
    _check_size(size)
    z_bounds, step_bounds = FAMILY_SIZES[size]["z_half_nm"], FAMILY_SIZES[size]["z_step_nm"]
    rng = np.random.default_rng([28, seed])
    medium = str(rng.choice(list(MEDIA)))
    n, na_lo, na_hi = MEDIA[medium]
    na = float(rng.uniform(na_lo, na_hi))
    wavelength = float(rng.uniform(500.0, 700.0))
    # astigmatism of focal lines `separation` apart: defocus ∓ sqrt(6) a rho^2 = z NA^2 rho^2/2n
    separation = float(rng.uniform(0.0, 1000.0))
    astig = separation * na**2 / (4 * np.sqrt(6) * n)
    angle = float(rng.uniform(0, np.pi))
    mean = {"astig_oblique": astig * np.sin(angle), "astig_vertical": astig * np.cos(angle),
            "coma_x": float(rng.normal(0, 10)), "coma_y": float(rng.normal(0, 10)),
            "spherical": float(rng.uniform(-25, 25))}  # fmt: skip
    std = {mode: float(rng.uniform(2.0, 10.0)) for mode in MODES}
    std["spherical"] /= 2
    depth = wavelength * n / na**2
    z_half = float(np.clip(rng.uniform(2.0, 4.0) * depth, *z_bounds))
    step = float(np.clip(np.round(depth * rng.uniform(0.04, 0.12), -1), *step_bounds))
    lo = 10 ** rng.uniform(2.7, 3.5)
    return Draw(
        seed=seed,
        size=size,
        medium=medium,
        na=na,
        wavelength_nm=wavelength,
        pixel_size_nm=float(rng.uniform(65.0, 160.0)),
        form=str(rng.choice(FORMS)),
        mean_nm=mean,
        std_nm=std,
        curvature_nm=float(rng.uniform(-300.0, 300.0)),
        tilt_mrad=float(rng.uniform(0.0, 3.0)),
        bead_nm=float(rng.choice([0.0, rng.uniform(20.0, 200.0)])),
        photons=_log_uniform(rng, 5e4, 5e5),
        background=_log_uniform(rng, 1.0, 20.0),
        test_photons=(float(lo), float(10 * lo)),
        z_half_nm=z_half,
        z_step_nm=step,
        grid_fraction=float(rng.uniform(0.0, 1.0)),
    )


def _check_size(size: str) -> None:
    if size not in FAMILY_SIZES:
        raise ValueError(f"Expected `size` to be one of {tuple(FAMILY_SIZES)}, got {size!r}.")


def family_data(draw: Draw, size: str | None = None, renders: Path | None = None) -> ValidationData:
    """Calibration stacks and test frames of ``draw`` at one of :data:`FAMILY_SIZES` (the
    draw's own if None). With ``renders`` (a folder of your own), read them from there if this
    draw was imaged before by the same optics code, else image them and keep them there."""
    size = draw.size if size is None else size
    _check_size(size)
    if renders is None:
        return _render(draw, size)
    path = Path(renders) / f"{size}-{draw.seed}-{_render_key(draw, size)}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    data = _render(draw, size)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL))
    return data


def _render_key(draw: Draw, size: str) -> str:
    """12 hex digits naming the draw, the size and the source of the modules that image it."""
    folder = Path(__file__).parent
    sources = b"".join((folder / f"{name}.py").read_bytes() for name in RENDER_MODULES)
    return hashlib.sha256(f"{draw!r} {size}".encode() + sources).hexdigest()[:12]


def _render(draw: Draw, size: str) -> ValidationData:
    p = FAMILY_SIZES[size]
    lo, hi = p["grid"]
    layout = {**p, "grid": int(round(lo + draw.grid_fraction * (hi - lo))),
              "test_grid": int(np.ceil(np.sqrt(p["n_test"]))) + 1, "photons": draw.photons,
              "z_half_nm": draw.z_half_nm, "z_step_nm": draw.z_step_nm,
              "test_half_nm": round(2 * draw.z_half_nm / 3, -1)}  # fmt: skip
    camera = Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=draw.pixel_size_nm)
    rng = np.random.default_rng([28, draw.seed, 1])
    return simulate_study(layout, draw.microscope(p["patch_px"]), draw.fields(p["field_px"]),
                          camera, rng, background=draw.background, bead_nm=draw.bead_nm,
                          test_photons=draw.test_photons)  # fmt: skip

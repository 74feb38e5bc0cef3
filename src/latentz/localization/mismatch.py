"""Does the calibration fit a localization table as a whole? Two measurements, each with its error.

A calibration from another microscope or camera moves z wherever the spots' shapes can be
matched, so each spot may look consistent while the table as a whole is not. Two things the
z readout cannot absorb are measured over the table's converged, unique, located spots:

- **the astigmatism's axis**: the rotation of the spots' ellipticity against the calibration's
  at each spot's z, half the angle of Σ E_spot · conj(E_curve(z)), where E = e1 + i e2
  (:func:`latentz.calibration.shape.ellipticity`) points at 2θ for an image elongated along θ.
  Scatter of a spot's E enters this sum once, times the calibration's E, whose sign flips
  through focus, so it widens the angle's standard error (from resampling the spots) rather
  than turning it. The angle is judged only where the terms add up to a direction: their
  resultant's squared length over the sum of their squared lengths, |Σ m|² / Σ |m|² (a
  Rayleigh statistic weighted by the terms' lengths, 1 on average for terms of random phase),
  at least :data:`MIN_RESULTANT`, or in a table of :data:`AXIS_BOOTSTRAP_SPOTS` spots or more.
  Below both the angle of the sum is undefined and its resampled error too small: tables of
  20–80 spots of a very weakly astigmatic microscope then blamed their right calibration. The
  spots' own summed E² (the axis that :func:`~latentz.calibration.shape.astigmatism_angle`
  finds) holds that scatter squared: where it differs in e1 and e2 and outweighs a weak
  astigmatism, it turns the spots' axis by up to 45° against a right calibration's. A wrong
  calibration reads each z where its rotated shapes come nearest the spot's, near focus where
  its E is small and of either sign, so a 45° rotation reads as 1–30° here
  (:data:`AXIS_LIMIT_DEG`);
- **the widths**, each spot's carried to its calibration particle's brightness by the
  calibration's own dimmed refits (:mod:`latentz.calibration.dimming`: how the Gaussian fit of
  this microscope's PSF widens or narrows as the emitter dims, which differs from microscope
  to microscope), against the calibration's at the spot's z, two ways: the median log ratio
  of the mean widths
  (another pixel size scales every width up or down), and the median **blur**, the calibration's
  squared widths less the spot's (nm², the mean over x and y), read as the σ of a blur: a
  particle's image is the PSF blurred by the particle (σ = 0.22 × its diameter for a sphere,
  22 nm for a 100 nm bead), added in quadrature at every z, so a point molecule falls short of
  it by that blur however wide the astigmatism makes both. A calibration made at a longer
  wavelength falls short by far more (about 60 nm at 1.2x), where a width ratio is diluted
  by the astigmatic spread of strongly astigmatic images.

Each width measurement's standard error holds the spots' scatter and the calibration's own
uncertainty: a spot is compared with its nearest particle's curves, which stand for the spot's
place only as well as neighbouring particles agree (:func:`_calibration_se`).

The calibration is blamed when the axis (where judged) lies more than :data:`AXIS_LIMIT_DEG`
off, the log width ratio above :data:`LOG_WIDTH_LIMIT` or the blur beyond
:data:`BLUR_LIMIT_NM`, by more than :data:`SIGNIFICANCE` standard errors. A
calibration whose astigmatism lies 90° off is not seen: it reads every z mirrored (z → −z), and
the shapes fit as well as the right calibration's; only the PSF's asymmetry about focus tells
them apart.
Limits and measurements: ``benchmarks/bench_wrong_calibration.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.sanity import warn
from latentz.calibration.shape import ellipticity

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["Mismatch", "calibration_mismatch", "check_calibration_fits"]

#: Rotation (degrees) of the spots' ellipticity against the calibration's beyond which the
#: calibration is blamed. Right calibrations give within ±5.2° (± 0.4–4.9°; 17 of 21 within
#: one standard error) on 21 microscopes of 3–90 nm RMS astigmatism and 6 more of 3–8 nm (widths
#: within 0.93–1.08 of each other over ±400 nm). One whose astigmatism lies 45° off gives −30° to
#: +30°: blamed by this angle on 7 of 13 very weakly astigmatic microscopes and on none of 14
#: stronger ones (the two beyond 10° read a resultant below :data:`MIN_RESULTANT`), where the
#: width checks blame 12 of 14; those missed that were measured
#: against the truth (2 weak, 2 very weak) double the z error
#: (benchmarks/bench_wrong_calibration.py, docs/single-molecules.md).
AXIS_LIMIT_DEG = 10.0
#: Least resultant statistic |Σ m|² / Σ |m|² at which the axis is judged. Of 200 random draws
#: each of 20, 40, 80 and 160 spots from the right tables of 21 microscopes (12 of very weak
#: astigmatism, 7 weak, 2 strong), the axis alone blamed 108, 47, 1 and 0 (of 4200, 4200, 4200
#: and 4000), all on very weak ones and at 18.4 or less, 1 of them at 15 or more; tables of
#: 180–370 spots with a calibration turned by 45° that the axis blamed read 25–69 (very weak
#: astigmatism; 11 and 15 on two weak microscopes whose widths blame them too), right ones
#: 18–194 (benchmarks/bench_wrong_calibration.py, docs/single-molecules.md). It cannot exceed the
#: number of spots: a table of 20 is judged by its axis only where all its terms align.
MIN_RESULTANT = 20.0
#: Spots from which the resampled error of the axis holds its spread whatever the resultant:
#: the draws above blamed 1 right table in 4200 at 80 spots and none in 4000 at 160, and the
#: fit3Dcspline bead (129 planes) under the SMLM 2016 calibration reads −43 ± 5° at a resultant
#: of 7 (tests/pipeline/test_quality.py).
AXIS_BOOTSTRAP_SPOTS = 100
#: The spots' log width ratio (at the calibration's brightness) above which they are wider than
#: a right calibration's: 100 nm beads against point molecules of 10³–10⁴ photons give −0.053 to
#: −0.018 (±0.003–0.005) on 8 random microscopes of 20–90 nm RMS astigmatism, point particles
#: (draw 17) and 161 nm beads (draw 19) against point emitters on the high-NA family draws (their
#: default calibrations and test frames, full and ci size) −0.008 to +0.005 (±0.002–0.015);
#: another pixel size (1.25x) gives +0.074 to +0.078 (benchmarks/bench_wrong_calibration.py).
LOG_WIDTH_LIMIT = 0.04
#: Blur (σ, nm) by which the spots' widths may fall short of the calibration's: 100 nm beads
#: against point molecules of 10³–10⁴ photons give +30 to +39 nm (±1–3 nm) on 8 random
#: microscopes of 20–90 nm RMS astigmatism; on the high-NA family draws 17 (point particles) and
#: 19 (161 nm beads, whose blur is 35 nm) ±19 nm; a calibration at 1.2x the wavelength gives +64
#: to +74 nm on 12 (benchmarks/bench_wrong_calibration.py). 50 nm is the blur of a 220 nm
#: sphere.
BLUR_LIMIT_NM = 50.0
#: Change of a spot's log mean width per unit of log photons, for calibrations without dimmed
#: refits only (files written before them): dim spots fit narrower with a scalar PSF (the
#: Gaussian sees less of its wings), 0.018–0.068, median 0.035, on the microscopes of
#: benchmarks/bench_wrong_calibration.py; the vectorial PSF of a high-NA objective fits wider
#: instead (family draws 17 and 19, oil NA 1.47 and 1.49), which the refits measure.
PHOTON_SLOPE = 0.035
#: Standard errors by which a measurement must lie beyond its limit to blame the calibration
#: (the width limits lie 1.3 or more standard errors beyond every right calibration measured:
#: the least, the blur of family draw 19's 22 spots at the ci size, −377 ± 2250 nm² against
#: the limit's 2500 nm²).
SIGNIFICANCE = 1.0
#: Fewest checked spots that measure anything.
MIN_SPOTS = 20
_RESAMPLES = 200


class Mismatch(NamedTuple):
    """What :func:`calibration_mismatch` measures (NaN where too few spots)."""

    axis_deg: float  #: spots' ellipticity turned from the calibration's at their z, ° in [−45, 45)
    axis_se_deg: float
    axis_resultant: float  #: |Σ m|² / Σ |m|² of the axis's terms (:data:`MIN_RESULTANT`)
    log_width: float  #: log of the spots' mean width over the calibration's
    log_width_se: float
    blur_nm2: float  #: the calibration's squared widths less the spots', nm²
    blur_se_nm2: float
    spots: int

    @property
    def blur_nm(self) -> float:
        """The blur as a σ (nm), negative where the spots are the wider."""
        return float(np.sign(self.blur_nm2) * np.sqrt(abs(self.blur_nm2)))

    @property
    def axis_off(self) -> bool:
        beyond = abs(self.axis_deg) - SIGNIFICANCE * self.axis_se_deg > AXIS_LIMIT_DEG
        judged = self.axis_resultant >= MIN_RESULTANT or self.spots >= AXIS_BOOTSTRAP_SPOTS
        return bool(judged and beyond)

    @property
    def widths_off(self) -> bool:
        wider = self.log_width - SIGNIFICANCE * self.log_width_se > LOG_WIDTH_LIMIT
        return wider or self.blur_nm2 - SIGNIFICANCE * self.blur_se_nm2 > BLUR_LIMIT_NM**2


def _checked(table: pd.DataFrame) -> np.ndarray:
    """Converged, unique spots that the calibration located."""
    ok = table["converged"].to_numpy(bool) & np.isfinite(table["z_nm"].to_numpy(float))
    return ok & ~table["duplicate"].to_numpy(bool)


def _spin(wx: np.ndarray, wy: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Ellipticity E = e1 + i e2 of shapes (wx, wy, ρ)."""
    e1, e2 = ellipticity(wx, wy, rho)
    return e1 + 1j * e2


def _axis(spots: pd.DataFrame, cal: Calibration, seed: int) -> tuple[float, float, float]:
    """Rotation (rad, in [−π/4, π/4)) of the spots' ellipticity against their particle's curves
    at their z, half the angle of Σ m with m = E_spot · conj(E_curve), its standard error over
    :data:`_RESAMPLES` resamples of the spots, and the resultant statistic |Σ m|² / Σ |m|²."""
    curves = cal.curves_at(spots["cal_particle"].to_numpy(int), spots["z_nm"].to_numpy(float))
    spot = _spin(*(spots[c].to_numpy(float) for c in ("wx", "wy", "rho")))
    match = spot * np.conj(_spin(curves["wx"], curves["wy"], curves["rho"]))
    match = match[np.isfinite(match)]
    angle = _wrap(np.angle(match.sum()) / 2)
    draws = np.random.default_rng(seed).integers(0, match.size, (_RESAMPLES, match.size))
    spread = _wrap(np.angle(match[draws].sum(axis=1)) / 2 - angle)
    resultant = abs(match.sum()) ** 2 / np.sum(np.abs(match) ** 2)
    return float(angle), float(np.std(spread)), float(resultant)


def _wrap(angle: np.ndarray | float) -> np.ndarray | float:
    """Angle (rad) folded into [−π/4, π/4): an axis is defined modulo π/2."""
    return (angle + np.pi / 4) % (np.pi / 2) - np.pi / 4


def _median(values: np.ndarray) -> tuple[float, float]:
    """Median of the finite ``values`` and its standard error (1.2533 robust standard
    deviations over √n)."""
    values = values[np.isfinite(values)]
    centre = float(np.median(values))
    spread = 1.4826 * float(np.median(np.abs(values - centre)))
    return centre, 1.2533 * spread / np.sqrt(values.size)


def _carried_widths(table: pd.DataFrame, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The spots' |wx|, |wy| (px) as their calibration particle's own, brighter fit would show
    them at their z: less the shift that the calibration's dimmed refits measure at each spot's
    brightness (:meth:`~latentz.calibration.Calibration.shapes_at_particle_brightness`); for a
    calibration without dimmed refits, or spots without a background, carried to the particles'
    median photons along :data:`PHOTON_SLOPE`."""
    shapes = cal.shapes_at_particle_brightness(table)
    if shapes is not None:
        return np.abs(shapes[:, 0]), np.abs(shapes[:, 1])
    reference = np.log(np.nanmedian(cal.traces["photons"][cal.kept]))
    carry = np.exp(PHOTON_SLOPE * (reference - np.log(table["photons"].to_numpy(float))))
    return carry * np.abs(table["wx"].to_numpy(float)), carry * np.abs(table["wy"].to_numpy(float))


def _curve_widths(cal: Calibration, p: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean width (px) and mean squared width (nm², of x and y) of particles ``p``'s curves at
    ``z`` (nm)."""
    curves = cal.curves_at(p, z)
    cx, cy = np.abs(curves["wx"]), np.abs(curves["wy"])
    return (cx + cy) / 2, (cx**2 + cy**2) / 2 * cal.camera.pixel_size_nm**2


def _held_out_differences(
    table: pd.DataFrame, cal: Calibration, mean_p: np.ndarray, square_p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """How far each spot's particle's curves at its z (``mean_p``, ``square_p``:
    :func:`_curve_widths` there) may lie from the truth at the spot's place, as held-out
    particles show it: the log ratio of the particle's mean widths over its nearest other kept
    particle's, and the difference of their mean squared widths (nm²), each scaled by the
    spot's distance from its particle over theirs; zeros with one kept particle."""
    p, z = table["cal_particle"].to_numpy(int), table["z_nm"].to_numpy(float)
    if cal.kept.size < 2:
        return np.zeros(z.size), np.zeros(z.size)
    kept_xy = cal.positions[cal.kept]
    spacing, nearest = cKDTree(kept_xy).query(kept_xy, k=2)
    row = np.searchsorted(cal.kept, p)  # p is a kept particle: its row in kept_xy
    q = cal.kept[nearest[row, 1]]
    xy = table[["x", "y"]].to_numpy(float)
    scale = np.hypot(*(xy - cal.positions[p]).T) / spacing[row, 1]
    mean_q, square_q = _curve_widths(cal, q, z)
    return scale * np.log(mean_p / mean_q), scale * (square_p - square_q)


def _calibration_se(
    table: pd.DataFrame, cal: Calibration, mean_p: np.ndarray, square_p: np.ndarray
) -> tuple[float, float]:
    """Standard errors that the calibration's own curves (``mean_p``, ``square_p`` at the
    spots' z: :func:`_curve_widths`) add to the spots' median log width ratio and blur (nm²):
    a particle's curves err alike for every spot near it, so each particle's median of
    :func:`_held_out_differences` over its spots, weighted by its share of the spots, in
    quadrature."""
    particle = table["cal_particle"].to_numpy(int)
    se = []
    for difference in _held_out_differences(table, cal, mean_p, square_p):
        median, size = _particle_medians(difference, particle)
        se.append(float(np.sqrt(np.nansum((median * size / particle.size) ** 2))))
    return se[0], se[1]


def _particle_medians(values: np.ndarray, particle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each particle's median of its spots' ``values`` (NaN left out; NaN where all are) and
    its number of spots, particles in ascending order."""
    order = np.lexsort((values, particle))  # by particle, then value, NaN last
    ordered, keys = values[order], particle[order]
    first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    size = np.diff(np.r_[first, keys.size])
    counted = np.add.reduceat(~np.isnan(ordered), first)
    lower, upper = first + np.maximum(counted - 1, 0) // 2, first + counted // 2
    return np.where(counted > 0, (ordered[upper] + ordered[lower]) / 2, np.nan), size


def _widths(table: pd.DataFrame, cal: Calibration) -> tuple[float, float, float, float]:
    """The spots' median log mean-width ratio over the calibration at their z and their
    median blur (nm², the calibration's mean squared width less the spot's), each with its
    standard error, the spots' and the calibration's own (:func:`_calibration_se`) in
    quadrature; every spot's widths carried to its particle's brightness
    (:func:`_carried_widths`)."""
    wx, wy = _carried_widths(table, cal)
    mean, square = _curve_widths(cal, table["cal_particle"].to_numpy(int),
                                 table["z_nm"].to_numpy(float))  # fmt: skip
    log_width, log_se = _median(np.log((wx + wy) / 2 / mean))
    blur, blur_se = _median(square - (wx**2 + wy**2) / 2 * cal.camera.pixel_size_nm**2)
    log_se, blur_se = np.hypot((log_se, blur_se), _calibration_se(table, cal, mean, square))
    return log_width, float(log_se), blur, float(blur_se)


def calibration_mismatch(table: pd.DataFrame, calibration: Calibration) -> Mismatch:
    """The axis and width-scale measurements of the module docstring for a table that
    ``calibration`` located (its ``z_nm`` and ``cal_particle`` columns)."""
    checked = _checked(table)
    n = int(checked.sum())
    if n < MIN_SPOTS:
        return Mismatch(*[np.nan] * 7, n)
    spots = table[checked]
    axis, axis_se, resultant = _axis(spots, calibration, seed=n)
    return Mismatch(
        float(np.degrees(axis)), float(np.degrees(axis_se)), resultant,
        *_widths(spots, calibration), n,
    )  # fmt: skip


def _cause(mismatch: Mismatch) -> str:
    """The likely cause of a mismatch, in words."""
    causes = []
    if mismatch.axis_off:
        causes.append(
            f"their astigmatism lies along other axes than the calibration's "
            f"({mismatch.axis_deg:+.0f}° ± {mismatch.axis_se_deg:.0f}°): another microscope, "
            "or a rotated camera"
        )
    if mismatch.widths_off and mismatch.blur_nm > BLUR_LIMIT_NM:
        causes.append(
            f"their widths fall short of the calibration's by a blur of {mismatch.blur_nm:.0f} "
            f"nm (σ; a 100 nm bead blurs by 22 nm): emitters smaller than the calibration "
            "particles, or another wavelength or objective"
        )
    elif mismatch.widths_off:
        causes.append(
            f"their widths are {np.exp(mismatch.log_width):.2g}x the calibration's: emitters "
            "larger than the calibration particles, another pixel size or objective, or "
            "astigmatism along other axes (a rotated camera)"
        )
    return "; ".join(causes)


def check_calibration_fits(table: pd.DataFrame, calibration: Calibration) -> pd.DataFrame:
    """``table``, or, when :func:`calibration_mismatch` blames the calibration, a copy with
    every spot ``inconsistent`` and not good, after one warning naming the cause: a calibration
    that contradicts the table cannot be trusted for the spots it happens to match."""
    if "inconsistent" not in table.columns:
        return table
    mismatch = calibration_mismatch(table, calibration)
    if not (mismatch.axis_off or mismatch.widths_off):
        return table
    warn(
        f"The calibration does not fit these data ({_cause(mismatch)}); every spot is flagged "
        "`inconsistent` and not good. Calibrate on this microscope and camera, with emitters "
        "like those you measure (beads of at most 100 nm for single molecules)."
    )
    return table.assign(inconsistent=True, good=False)

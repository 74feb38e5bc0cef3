"""Does the calibration fit a localization table as a whole? Two measurements, each with its error.

A calibration from another microscope or camera moves z wherever the spots' shapes can be
matched, so each spot may look consistent while the table as a whole is not. Two things the
z readout cannot absorb are measured over the table's converged, unique, located spots:

- **the astigmatism's axis**: the turn of the calibration's curves that fits the spots best.
  Each spot's shape (wx, wy, ρ, carried to its particle's brightness as the widths below) is
  compared, by the χ² of ``consistency_chi2``, with its particle's curves turned by each of
  :data:`TURNS`, at the z within its in-range window where they fit best, capped at
  :data:`AXIS_CHI2_CAP`; turns 90° apart count as one (an axis is defined modulo 90°, and a
  90° turn mirrors z), and the turn of least summed χ² is the axis, with the χ² it gains over
  the curves as they are. Both have standard errors from resampling the spots. Reading each
  spot at its own best z for every turn matters: a calibration turned by 45° reads z where its
  shapes come nearest the spot's, near focus where its ellipticity is small and of either sign,
  and the spots' ellipticity against the calibration's at that z turns by only up to 33°. Blamed
  beyond :data:`AXIS_LIMIT_DEG` with a gain beyond :data:`AXIS_GAIN_SIGNIFICANCE` standard
  errors: on very weak astigmatism, where a turn barely changes the curves, a right
  calibration's best turn lies up to 28° off by chance, but gains little;
- **the widths**, each spot's carried to its calibration particle's brightness by the
  calibration's own dimmed refits (:mod:`latentz.calibration.dimming`: how the Gaussian fit of
  this microscope's PSF widens or narrows as the emitter dims, which differs from microscope
  to microscope), against the calibration's at the spot's z, over the spots whose ROI holds
  no other fit (a neighbour's light widens a spot), two ways: the median log ratio of the mean
  widths
  (another pixel size scales every width up or down), and the median **blur**, the calibration's
  squared widths less the spot's (nm², the mean over x and y), read as the σ of a blur: a
  particle's image is the PSF blurred by the particle (σ = 0.22 × its diameter for a sphere,
  22 nm for a 100 nm bead), added in quadrature at every z, so a point molecule falls short of
  it by that blur however wide the astigmatism makes both (unless ``calibrate`` was given the
  particles' diameter, which takes the blur off the calibration). A calibration made at a longer
  wavelength falls short by far more (about 60 nm at 1.2x), where a width ratio is diluted
  by the astigmatic spread of strongly astigmatic images.

Each width measurement's standard error holds the spots' scatter and the calibration's own
uncertainty: a spot is compared with its nearest particle's curves, which stand for the spot's
place only as well as neighbouring particles agree (:func:`_calibration_se`).

The calibration is blamed when the axis lies more than :data:`AXIS_LIMIT_DEG` off with a
significant gain, the log width ratio above :data:`LOG_WIDTH_LIMIT` or the blur beyond
:data:`BLUR_LIMIT_NM`, by more than :data:`SIGNIFICANCE` standard errors. A
calibration whose astigmatism lies 90° off is not seen: it reads every z about mirrored
(z → −z), and the shapes fit as well as the right calibration's. The PSF's asymmetry about
focus does not tell them apart either: each of the two fits the spots better as it is than
turned by 90° (docs/single-molecules.md).
Limits and measurements: ``benchmarks/bench_wrong_calibration.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.sanity import warn
from latentz.localization.pairs import crowded
from latentz.localization.quality import curve_share2

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["Mismatch", "calibration_mismatch", "check_calibration_fits"]

#: Turn (degrees) of the calibration's curves, fitting the spots best, beyond which the
#: calibration is blamed. Right calibrations turn by at most 2.5° (± 0–1.4°) on microscopes of
#: 20–90 nm RMS astigmatism and by up to 27.5° (± 2–12.5°) by chance on those of 3–8 nm, where a
#: turn barely changes the curves; one whose astigmatism lies 45° off turns by 30–45° (± 0–3.6°)
#: on all of them (benchmarks/bench_wrong_calibration.py, docs/single-molecules.md).
AXIS_LIMIT_DEG = 10.0
#: Standard errors by which the χ² that turn gains must exceed zero to blame the calibration.
#: Right calibrations gain at most 2.5 standard errors (on 3–8 nm RMS astigmatism; 0–1.4 on
#: stronger), and none of 6,300 tables of 20–80 of their spots is blamed; a calibration turned
#: by 45° gains 4.0–10 on microscopes of 3–8 nm (3.98 on one of 14: missed), 10–22 on 20–30 nm
#: and 16–34 on 50–90 nm (the same sources).
AXIS_GAIN_SIGNIFICANCE = 4.0
#: Turns (rad) of the calibration's curves tried: every 2.5° over 180°.
TURNS = np.radians(np.arange(-90.0, 90.0, 2.5))
#: Step (nm) of the z at which each turned curve is compared with a spot.
Z_STEP_NM = 10.0
#: Most χ² one spot adds to a turn's sum: χ²(2)'s 99.9 % point, so that a spot no turn fits
#: (a neighbour's light) does not choose the turn.
AXIS_CHI2_CAP = 13.8
#: Most spots the axis is measured on (drawn at random from larger tables): more than the
#: 200–300 checked spots of each table of benchmarks/bench_wrong_calibration.py, so that the
#: hits and false alarms measured there hold, while the check costs at most about 0.3 s of CPU.
AXIS_SPOTS = 400
#: The log width ratio (at the calibration's brightness) of the spots whose ROI holds no other
#: fit above which they are wider than a right calibration's. A calibration's particles are
#: points or beads, never smaller than molecules, so a right calibration's ratio lies at or below
#: zero: 100 nm beads against point molecules of 10³–10⁴ photons give −0.064 to −0.020
#: (±0.002–0.011) on the 21 right calibrations of benchmarks/bench_wrong_calibration.py
#: (3–90 nm RMS astigmatism), and −0.044 to −0.006 (±0.006–0.008) on six random microscopes
#: (seeds 0–5) at 2 molecules per µm²; points on the high-NA family draw 17 (NA 1.47)
#: +0.002 ± 0.002 at the full size, −0.009 ± 0.013 at the ci size; 161 nm beads on draw 19
#: −0.026 ± 0.003. Another pixel size (1.25x) gives +0.063 to +0.083 on the benchmark's
#: microscopes and +0.048 ± 0.009 on that of tests/pipeline/test_verdicts_truth.py, where the
#: dim spots' z readout takes up much of the scale.
LOG_WIDTH_LIMIT = 0.02
#: Blur (σ, nm) by which the spots' widths may fall short of the calibration's: 100 nm beads
#: against point molecules of 10³–10⁴ photons give +28 to +45 nm (±2–4 nm) on the 21 right
#: calibrations, and a calibration at 1.2x the wavelength +63 to +78 nm on 21
#: (benchmarks/bench_wrong_calibration.py); family draw 17 (point particles) −14 nm. 50 nm is the
#: blur of a 220 nm sphere. Family draw 19's 161 nm beads blur by 35 nm as spheres, but its
#: point emitters fall short of them by 58 ± 4 nm at NA 1.49: a calibration on beads that large,
#: without their diameter (``calibrate(..., particle_diameter_nm=)``), is blamed there.
BLUR_LIMIT_NM = 50.0
#: Change of a spot's log mean width per unit of log photons, for calibrations without dimmed
#: refits only (files written before them): dim spots fit narrower with a scalar PSF (the
#: Gaussian sees less of its wings), 0.018–0.068, median 0.035, on the microscopes of
#: benchmarks/bench_wrong_calibration.py; the vectorial PSF of a high-NA objective fits wider
#: instead (family draws 17 and 19, oil NA 1.47 and 1.49), which the refits measure.
PHOTON_SLOPE = 0.035
#: Standard errors by which a measurement must lie beyond its limit to blame the calibration
#: (the width limits lie 1.7 or more standard errors beyond every right calibration of 100 nm
#: beads or points measured: the least, the blur of the strong microscope 511 of
#: benchmarks/bench_wrong_calibration.py, +45 ± 3 nm against the limit's 50 nm).
SIGNIFICANCE = 1.0
#: Fewest checked spots that measure anything.
MIN_SPOTS = 20
_RESAMPLES = 200
_SHAPE = ("wx", "wy", "rho")


class Mismatch(NamedTuple):
    """What :func:`calibration_mismatch` measures (NaN where too few spots)."""

    axis_deg: float  #: turn of the calibration's curves that fits the spots best, ° in [−45, 45)
    axis_se_deg: float
    axis_gain: float  #: the spots' summed shape χ² less with that turn than without
    axis_gain_se: float
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
        return bool(beyond and self.axis_gain > AXIS_GAIN_SIGNIFICANCE * self.axis_gain_se)

    @property
    def widths_off(self) -> bool:
        wider = self.log_width - SIGNIFICANCE * self.log_width_se > LOG_WIDTH_LIMIT
        return wider or self.blur_nm2 - SIGNIFICANCE * self.blur_se_nm2 > BLUR_LIMIT_NM**2


def _checked(table: pd.DataFrame) -> np.ndarray:
    """Converged, unique spots that the calibration located."""
    ok = table["converged"].to_numpy(bool) & np.isfinite(table["z_nm"].to_numpy(float))
    return ok & ~table["duplicate"].to_numpy(bool)


def _moments(
    wx: np.ndarray, wy: np.ndarray, rho: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second moments of shapes (wx, wy in px, ρ) as (xx + yy) / 2, (xx − yy) / 2 and xy (px²),
    from which :func:`_turned` turns them."""
    xx, yy = wx**2, wy**2
    return (xx + yy) / 2, (xx - yy) / 2, rho * wx * wy


def _turned(
    mean: np.ndarray, half: np.ndarray, xy: np.ndarray, phi: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shapes (wx, wy in px, ρ) of images of :func:`_moments` ``mean``, ``half``, ``xy`` turned
    by ``phi`` (rad); turned by ``phi`` + π/2 they are (wy, wx, −ρ)."""
    c, s = np.cos(2 * phi), np.sin(2 * phi)
    swing = half * c - xy * s
    wx, wy = np.sqrt(mean + swing), np.sqrt(mean - swing)
    return wx, wy, (half * s + xy * c) / (wx * wy)


def _turn_chi2(spots: pd.DataFrame, cal: Calibration) -> np.ndarray:
    """(:data:`TURNS`, spots) each spot's shape χ² (wx, wy, ρ carried to its particle's
    brightness, σ of :func:`~latentz.localization.quality.curve_spread`) against its particle's
    curves turned by each of :data:`TURNS`, at the z (steps of :data:`Z_STEP_NM` within the
    spot's in-range window) where they fit best, capped at :data:`AXIS_CHI2_CAP`."""
    p, z = spots["cal_particle"].to_numpy(int), spots["z_nm"].to_numpy(float)
    window = cal.in_range_window(p, z)
    grid = np.arange(np.min(window[:, 0]), np.max(window[:, 1]) + Z_STEP_NM, Z_STEP_NM)
    particle, at = np.broadcast_arrays(p[:, None], grid)
    curves = {
        name: v.reshape(at.shape) for name, v in cal.curves_at(particle.ravel(), at.ravel()).items()
    }
    outside = (at < window[:, :1]) | (at > window[:, 1:])
    values = [v[:, None] for v in _carried_shapes(spots, cal)]
    fixed = [np.square(spots[f"{n}_err"].to_numpy(float)[:, None] if f"{n}_err" in spots else 0.0)
             + curves[f"{n}_scatter"] ** 2 for n in _SHAPE]  # fmt: skip
    moments = _moments(np.abs(curves["wx"]), np.abs(curves["wy"]), curves["rho"])
    half = TURNS.size // 2  # TURNS[k + half] is TURNS[k] + 90°: the same shapes, wx and wy swapped
    chi2 = np.empty((TURNS.size, len(spots)))
    for k in range(half):
        wx, wy, rho = _turned(*moments, TURNS[k])
        for row, shapes in ((k, (wx, wy, rho)), (k + half, (wy, wx, -rho))):
            turned = dict(zip(_SHAPE, shapes, strict=True))
            total = sum((v - turned[n]) ** 2 / (f + curve_share2(n, turned))
                        for n, v, f in zip(_SHAPE, values, fixed, strict=True))  # fmt: skip
            chi2[row] = np.min(np.where(outside, np.inf, total), axis=1)
    return np.minimum(chi2, AXIS_CHI2_CAP)


def _axis(spots: pd.DataFrame, cal: Calibration, seed: int) -> tuple[float, float, float, float]:
    """The turn (rad, in [−π/4, π/4)) of the calibration's curves that fits the spots best
    (least summed :func:`_turn_chi2`, turns 90° apart taken as one: an axis is defined modulo
    π/2), its standard error, and the χ² it gains over the curves as they are, with its
    standard error, all over :data:`_RESAMPLES` resamples of the spots; at most
    :data:`AXIS_SPOTS` of them, drawn at random."""
    rng = np.random.default_rng(seed)
    if len(spots) > AXIS_SPOTS:
        spots = spots.iloc[np.sort(rng.choice(len(spots), AXIS_SPOTS, replace=False))]
    chi2 = _turn_chi2(spots, cal)
    chi2 = chi2[:, np.all(np.isfinite(chi2), axis=0)]
    half = TURNS.size // 2  # TURNS[k + half] is TURNS[k] + 90°
    folded = np.minimum(chi2[:half], chi2[half:])
    turns, none = _wrap(TURNS[:half]), np.argmin(np.abs(_wrap(TURNS[:half])))

    def fit(total: np.ndarray) -> tuple[float, float]:
        best = int(np.argmin(total))
        return float(turns[best]), float(total[none] - total[best])

    angle, gain = fit(folded.sum(axis=1))
    draws = rng.integers(0, chi2.shape[1], (_RESAMPLES, chi2.shape[1]))
    resampled = np.array([fit(folded[:, draw].sum(axis=1)) for draw in draws])
    spread = _wrap(resampled[:, 0] - angle)
    return angle, float(np.std(spread)), gain, float(np.std(resampled[:, 1]))


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


def _carried_shapes(
    table: pd.DataFrame, cal: Calibration
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spots' |wx|, |wy| (px) and ρ as their calibration particle's own, brighter fit would
    show them at their z: less the shift that the calibration's dimmed refits measure at each
    spot's brightness (:meth:`~latentz.calibration.Calibration.shapes_at_particle_brightness`);
    for a calibration without dimmed refits, or spots without a background, the widths carried
    to the particles' median photons along :data:`PHOTON_SLOPE` and ρ as fitted."""
    shapes = cal.shapes_at_particle_brightness(table)
    if shapes is not None:
        return np.abs(shapes[:, 0]), np.abs(shapes[:, 1]), shapes[:, 2]
    reference = np.log(np.nanmedian(cal.traces["photons"][cal.kept]))
    carry = np.exp(PHOTON_SLOPE * (reference - np.log(table["photons"].to_numpy(float))))
    wx, wy, rho = (table[c].to_numpy(float) for c in _SHAPE)
    return carry * np.abs(wx), carry * np.abs(wy), rho


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
    """The spots' median log mean-width ratio over the calibration at their z and their median
    blur (nm², the calibration's mean squared width less the spot's), each with its standard
    error, the spots' and the calibration's own (:func:`_calibration_se`) in quadrature; every
    spot's widths carried to its particle's brightness (:func:`_carried_shapes`); NaN for fewer
    than :data:`MIN_SPOTS` spots."""
    if len(table) < MIN_SPOTS:
        return np.nan, np.nan, np.nan, np.nan
    wx, wy, _ = _carried_shapes(table, cal)
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
        return Mismatch(*[np.nan] * 8, n)
    spots = table[checked]
    axis, axis_se, gain, gain_se = _axis(spots, calibration, seed=n)
    alone = checked & ~crowded(table, (calibration.roi_size - 1) / 2)
    return Mismatch(
        float(np.degrees(axis)), float(np.degrees(axis_se)), gain, gain_se,
        *_widths(table[alone], calibration), n,
    )  # fmt: skip


def _cause(mismatch: Mismatch) -> str:
    """The likely cause of a mismatch, in words."""
    causes = []
    if mismatch.axis_off:
        causes.append(
            f"their astigmatism lies along other axes than the calibration's (its curves fit "
            f"them best turned by {mismatch.axis_deg:+.0f}° ± {mismatch.axis_se_deg:.0f}°): "
            "another microscope, or a rotated camera"
        )
    if mismatch.widths_off and mismatch.blur_nm > BLUR_LIMIT_NM:
        causes.append(
            f"their widths fall short of the calibration's by a blur of {mismatch.blur_nm:.0f} "
            f"nm (σ; a 100 nm bead blurs by 22 nm): emitters smaller than the calibration "
            "particles (calibrate with particle_diameter_nm= the beads' diameter to read point "
            "emitters), or another wavelength or objective"
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

"""Does the calibration fit a localization table as a whole? Two measurements, each with its error.

A calibration from another microscope or camera moves z wherever the spots' shapes can be
matched, so each spot may look consistent while the table as a whole is not. Two things the
z readout cannot absorb are measured over the table's converged, unique, located spots:

- **the astigmatism's axis**: the angle of the spots' summed E² (E = e1 + i e2, the ellipticity
  of :func:`latentz.calibration.shape.ellipticity`; its direction is 4θ on both sides of focus,
  as :func:`~latentz.calibration.shape.astigmatism_angle` uses it) against that of the
  calibration's own trace points. Each angle's standard error comes from resampling its spots or
  trace points, so a weakly astigmatic calibration (round images, a poorly known axis) or few
  dim spots widen it;
- **the width scale**: the median over the spots of their mean width over the calibration's at
  their z, as a log ratio, each carried to the calibration particles' photons along
  :data:`PHOTON_SLOPE` (dim spots fit narrower: the Gaussian sees less of the PSF's wings).
  A point molecule looks a little narrower than the bead it was calibrated with; another pixel
  size scales every width, and another wavelength the in-focus ones.

The calibration is blamed when the axis lies more than :data:`AXIS_LIMIT_DEG` off, or the width
scale outside :data:`LOG_WIDTH_BAND`, by more than :data:`SIGNIFICANCE` standard errors. A
calibration whose astigmatism lies 90° off is not seen: it reads every z mirrored (z → −z), and
the shapes fit as well as the right calibration's; only the PSF's asymmetry about focus tells
them apart.
Limits and measurements: ``benchmarks/bench_wrong_calibration.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pandas as pd

from latentz._shared.sanity import warn
from latentz.calibration.shape import ellipticity

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["Mismatch", "calibration_mismatch", "check_calibration_fits"]

#: Rotation (degrees) of the spots' astigmatism axis against the calibration's beyond which the
#: calibration is blamed: right calibrations give within ±2° (1–2 standard errors), one whose
#: astigmatism lies 45° off gives 43–44°.
AXIS_LIMIT_DEG = 10.0
#: Band of the spots' log width ratio (at the calibration's photons) that a right calibration
#: gives: 100 nm beads against point molecules of 10³–10⁴ photons give −0.048 to +0.014
#: (±0.004–0.014) on 12 tables of 10 random microscopes at 0.5–1.5 molecules per µm²; another
#: pixel size (1.25x) gives +0.074 and +0.090, another wavelength (1.2x) −0.115 and −0.160
#: (benchmarks/bench_wrong_calibration.py, tests/pipeline/test_verdicts_truth.py).
LOG_WIDTH_BAND = (-0.075, 0.04)
#: Change of a spot's log mean width per unit of log photons: dim spots fit narrower (the
#: Gaussian sees less of the PSF's wings). Measured 0.018–0.068, median 0.035, on the right and
#: wrong calibrations of benchmarks/bench_wrong_calibration.py (0.5 molecules per µm²); fixed,
#: since in crowded frames merged neighbours make the brightest spots wide and steepen a fit.
PHOTON_SLOPE = 0.035
#: Standard errors by which a measurement must lie beyond its limit to blame the calibration
#: (the limits lie 2.4 or more standard errors beyond every right calibration measured).
SIGNIFICANCE = 1.0
#: Fewest checked spots that measure anything.
MIN_SPOTS = 20
_RESAMPLES = 200


class Mismatch(NamedTuple):
    """What :func:`calibration_mismatch` measures (NaN where too few spots)."""

    axis_deg: float  #: spots' astigmatism axis minus the calibration's, degrees in [−45, 45)
    axis_se_deg: float
    log_width: float  #: log of the spots' mean width over the calibration's
    log_width_se: float
    spots: int

    @property
    def axis_off(self) -> bool:
        return abs(self.axis_deg) - SIGNIFICANCE * self.axis_se_deg > AXIS_LIMIT_DEG

    @property
    def widths_off(self) -> bool:
        low, high = LOG_WIDTH_BAND
        margin = SIGNIFICANCE * self.log_width_se
        return self.log_width + margin < low or self.log_width - margin > high


def _checked(table: pd.DataFrame) -> np.ndarray:
    """Converged, unique spots that the calibration located."""
    ok = table["converged"].to_numpy(bool) & np.isfinite(table["z_nm"].to_numpy(float))
    return ok & ~table["duplicate"].to_numpy(bool)


def _axis(wx: np.ndarray, wy: np.ndarray, rho: np.ndarray, seed: int) -> tuple[float, float]:
    """Astigmatism axis (rad, from the summed E²) of shapes (wx, wy, ρ) and its standard error
    over :data:`_RESAMPLES` resamples of them."""
    e1, e2 = ellipticity(wx, wy, rho)
    spin = ((e1 + 1j * e2) ** 2).ravel()
    spin = spin[np.isfinite(spin)]
    angle = np.angle(spin.sum()) / 4
    draws = np.random.default_rng(seed).integers(0, spin.size, (_RESAMPLES, spin.size))
    spread = _wrap(np.angle(spin[draws].sum(axis=1)) / 4 - angle)
    return float(angle), float(np.std(spread))


def _wrap(angle: np.ndarray | float) -> np.ndarray | float:
    """Angle (rad) folded into [−π/4, π/4): an axis is defined modulo π/2."""
    return (angle + np.pi / 4) % (np.pi / 2) - np.pi / 4


def _log_width(table: pd.DataFrame, cal: Calibration) -> tuple[float, float]:
    """Median log mean-width ratio of the spots over the calibration at their z, each spot's
    carried to the calibration particles' median photons along :data:`PHOTON_SLOPE`, and the
    median's standard error (1.2533 robust standard deviations over √n)."""
    z = table["z_nm"].to_numpy(float)
    curves = cal.curves_at(table["cal_particle"].to_numpy(int), z)
    spot = np.abs(table["wx"].to_numpy(float)) + np.abs(table["wy"].to_numpy(float))
    ratio = np.log(spot / (np.abs(curves["wx"]) + np.abs(curves["wy"])))
    reference = np.log(np.nanmedian(cal.traces["photons"][cal.kept]))
    ratio += PHOTON_SLOPE * (reference - np.log(table["photons"].to_numpy(float)))
    ratio = ratio[np.isfinite(ratio)]
    centre = float(np.median(ratio))
    spread = 1.4826 * float(np.median(np.abs(ratio - centre)))
    return centre, 1.2533 * spread / np.sqrt(ratio.size)


def calibration_mismatch(table: pd.DataFrame, calibration: Calibration) -> Mismatch:
    """The axis and width-scale measurements of the module docstring for a table that
    ``calibration`` located (its ``z_nm`` and ``cal_particle`` columns)."""
    checked = _checked(table)
    n = int(checked.sum())
    if n < MIN_SPOTS:
        return Mismatch(np.nan, np.nan, np.nan, np.nan, n)
    spots = table[checked]
    angle, se = _axis(*(spots[c].to_numpy(float) for c in ("wx", "wy", "rho")), seed=n)
    traces = calibration.traces
    kept = calibration.kept
    cal_angle, cal_se = _axis(*(traces[c][kept] for c in ("wx", "wy", "rho")), seed=n + 1)
    axis = np.degrees(_wrap(angle - cal_angle))
    log_width, log_se = _log_width(spots, calibration)
    return Mismatch(float(axis), float(np.degrees(np.hypot(se, cal_se))), log_width, log_se, n)


def _cause(mismatch: Mismatch) -> str:
    """The likely cause of a mismatch, in words."""
    causes = []
    if mismatch.axis_off:
        causes.append(
            f"their astigmatism lies along other axes than the calibration's "
            f"({mismatch.axis_deg:+.0f}° ± {mismatch.axis_se_deg:.0f}°): another microscope, "
            "or a rotated camera"
        )
    if mismatch.widths_off:
        ratio = float(np.exp(mismatch.log_width))
        causes.append(
            f"their widths are {ratio:.2g}x the calibration's: emitters "
            f"{'smaller' if ratio < 1 else 'larger'} than the calibration particles (a "
            "particle's image is the PSF blurred by the particle, so it changes with z unlike a "
            "point's), or another pixel size, wavelength or objective"
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

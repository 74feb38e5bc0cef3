"""Which shape parameter to localize with: the one with the best expected σ_z over the
calibrated range (``calibrate(shape=None)``) for single molecules, or, where no shape can
measure those, for emitters like the calibration particles.

Every candidate (``rho``, ``rho_w``, ``rho_A``, ``auto``, ``auto_A``) is judged on the same
planes: those where any candidate measures z well (the union of their
:func:`~latentz.calibration.precision.usable_planes` at 1000 photons) on the usable particles.

**Single molecules** (``score_nm``): on each plane the expected z error is the quadrature sum
of three independent errors:

- ``cv``: the cross-validated model error. Each particle's calibration images are localized with
  the nearest *other* particle's inverse model z(s) (leave one particle out), on the
  tilt-corrected axis. With a single particle, the local models' residual σ_z (corrected for
  the polynomial's degrees of freedom) stands in.
- ``crlb``: the fit's Cramér–Rao bound propagated to z for an emitter of 1000 photons, the
  geometric middle of single molecules' 100–10,000
  (:func:`~latentz.calibration.precision.crlb_sigma_z`); it scales close to 1/√N for every
  shape, so the ranking holds across that span.
- ``brightness`` (A-normalised shapes only): ρ_A and auto_A divide by A / A_{ρ=ρ0}, which holds
  only for emitters as bright as the calibration particles. An emitter of unknown brightness
  is off by its brightness ratio; the term is the z error for a ratio of
  :data:`BRIGHTNESS_RATIO` (either way), with values pushed out of the calibrated range counted
  as the range's half-length. Single molecules of 100–10,000 photons differ from 30,000-photon
  beads by far more, so A-normalised shapes win only when their advantage is large.

**Emitters like the calibration particles** (``particles_nm``): the cross-validated error on the
calibration's own images (their noise is in it), and for A-normalised shapes the ``brightness``
term too. Their held-out particle's images are normalised by the reference amplitude its
neighbours give it (:class:`~latentz.calibration.reference.ReferenceField`), as ``apply`` does,
so its own brightness counts; but the emitters such a calibration localizes are rarely exactly
as bright as its particles (single molecules on 100 nm beads: 2–20× dimmer), and nothing at
calibration tells the two uses apart. On 100 nm beads of 2·10⁴ photons under weak astigmatism
(65 nm pixels, ±400 nm) the cross-validated error alone would choose auto_A (34 against 57 nm
for auto), which localizes molecules of 10³–3·10³ / 3·10³–10⁴ photons to 260 / 137 nm z RMS; with
the brightness term auto is chosen (82 against 117 nm, at the 11 px ROI then chosen with it), and
gives them 152 / 72 nm.

Where a candidate cannot measure z (outside its monotonic range) its error is that of a guess
anywhere in the range (``guess_nm``: span/√12), and no plane counts worse than that. Each kind's
figure is the RMS of the expected error over the common planes, so a small σ_z over a short
range does not win.

Single molecules decide, so that the choice holds for emitters dimmer than the beads. But with
1 µm beads no shape measures a 1000-photon emitter (Cramér–Rao bounds of microns: every score
within a few tens of % of the guess), and the ranking of near-guesses is noise. Where no
shape's Cramér–Rao part alone (``photon_limit_nm``: the bound, capped at the guess, over the
common planes) is below :data:`GUESS_FRACTION` of the guess, the choice is made for the emitters
such a calibration serves, particles like its own (``particles_nm``). On the demo's stacks
(315 beads of 1 µm) single molecules' scores were 1264 nm for ρ_A and 1329 nm for auto against
a guess of 1726 nm; the beads' cross-validated 240 and 206 nm alone choose auto, and the gear's
z RMS went from 43 to 28 nm. The test is on the photon limit, not the score, because the score
also holds the cross-validated error, which any emitter has: three SMLM 2016 beads far apart
cross-validate at 300 nm for every shape, their scores all near the guess, while 1000-photon
molecules are measured there to 120 nm (auto).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.calibration.local import LocalModels
from latentz.calibration.precision import (
    REFERENCE_PHOTONS,
    crlb_sigma_z,
    image_crlb,
    usable_planes,
)
from latentz.calibration.reference import ReferenceField
from latentz.calibration.shape import uses_amplitude
from latentz.calibration.traces import Traces

__all__ = ["BRIGHTNESS_RATIO", "GUESS_FRACTION", "score_shapes", "choose"]

#: Brightness ratio (emitter / calibration particle) the A-normalised shapes are charged for.
BRIGHTNESS_RATIO = 2.0
#: Below this fraction of a guess's error (span/√12) a shape's Cramér–Rao bound measures
#: 1000-photon emitters; where none does, the choice is made for emitters like the calibration
#: particles.
GUESS_FRACTION = 0.5


def _rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2))) if values.size else np.nan


def _cross_validated(
    local: LocalModels, shape: str, use: np.ndarray, positions: np.ndarray, *,
    reference: bool = False,
) -> np.ndarray:  # fmt: skip
    """(n, n_z) z error (nm) of each particle's images localized with the nearest other usable
    particle's inverse model; the local residual σ_z for a lone particle.

    ``reference`` (A-normalised shapes): normalise each particle's images by the reference
    amplitude its neighbours give it (:meth:`~latentz.calibration.reference.ReferenceField.
    held_out`), as ``apply`` does, rather than by its own A_{ρ=ρ0}."""
    model = local.shapes[shape]
    rows = np.flatnonzero(use)
    if rows.size < 2:
        return model.sigma_z
    _, nearest = cKDTree(positions[rows]).query(positions[rows], k=2)
    scale = np.ones(len(model.values))
    if reference:
        field = ReferenceField(positions[rows], model.amplitude_ref[rows])
        scale[rows] = field.held_out() / model.amplitude_ref[rows]
    errors = np.full(model.values.shape, np.nan)
    for i, j in zip(rows, rows[nearest[:, 1]], strict=True):
        inverse = model.inverse[np.full(model.values.shape[1], j)]
        s = model.values[i] * scale[i]
        inside = inverse.contains(s) & np.isfinite(s)
        z = np.where(inside, inverse(np.where(inside, s, 0.0)), np.nan)
        errors[i] = z - local.z_nm[i]
    return errors


def _brightness(local: LocalModels, shape: str) -> np.ndarray:
    """(n, n_z) z error (nm) of images whose A_n is off by :data:`BRIGHTNESS_RATIO`, RMS over
    brighter and dimmer; out of range counts as half the calibrated range."""
    model = local.shapes[shape]
    half_range = np.abs(np.diff(model.z_range, axis=1)) / 2
    squares = []
    for ratio in (BRIGHTNESS_RATIO, 1 / BRIGHTNESS_RATIO):
        s = model.values / ratio
        inside = model.inverse.contains(s) & np.isfinite(s)
        z = model.inverse(np.where(inside, s, 0.0))
        squares.append(np.where(inside, z - local.z_nm, half_range) ** 2)
    return np.sqrt(np.mean(squares, axis=0))


def score_shapes(
    local: LocalModels,
    traces: Traces,
    use: np.ndarray,
    *,
    roi_size: int,
    readnoise: float,
    positions: np.ndarray,
) -> pd.DataFrame:
    """One row per modelled shape: ``cv_nm``, ``crlb_nm``, ``brightness_nm`` (RMS over the
    planes where the shape measures z), ``coverage`` (fraction of the common planes where it
    does), ``score_nm`` and ``particles_nm`` (the expected z error over the common planes for
    1000-photon emitters and for emitters like the calibration particles), ``photon_limit_nm``
    (the Cramér–Rao part of ``score_nm`` alone) and ``guess_nm``.

    ``local`` is on the tilt-corrected axis; ``use`` (n,) marks the particles to judge on.
    """
    bounds = image_crlb(traces, REFERENCE_PHOTONS, roi_size=roi_size, readnoise=readnoise)
    parts, common = {}, np.zeros(local.z_nm.shape, bool)
    for shape, model in local.shapes.items():
        valid = use & model.inverse.valid
        bound = crlb_sigma_z(
            local, traces, shape, REFERENCE_PHOTONS, roi_size=roi_size, bounds=bounds
        )
        cv = np.where(valid[:, None], _cross_validated(local, shape, valid, positions), np.nan)
        bright = _brightness(local, shape) if uses_amplitude(shape) else np.zeros_like(bound)
        own = cv
        if uses_amplitude(shape):
            own = _cross_validated(local, shape, valid, positions, reference=True)
            own = np.where(valid[:, None], own, np.nan)
        parts[shape] = (cv, bound, bright, own)
        common |= usable_planes(bound) & valid[:, None]
    z = np.where(common, local.z_nm, np.nan)[common.any(axis=1)]  # particles with common planes
    span = np.nanmax(z, axis=1) - np.nanmin(z, axis=1) if common.any() else np.zeros(1)
    guess = float(np.nanmean(span)) / np.sqrt(12.0) if common.any() else np.nan
    rows = []
    for shape, (cv, bound, bright, own) in parts.items():
        total = np.sqrt(cv**2 + bound**2 + bright**2)
        measured = common & np.isfinite(total)
        molecules = _rms(np.where(measured, np.minimum(total, guess), guess)[common])
        photons = _rms(np.where(measured, np.minimum(bound, guess), guess)[common])
        own = np.sqrt(own**2 + bright**2)
        own_ok = common & np.isfinite(own)
        particles = _rms(np.where(own_ok, np.minimum(own, guess), guess)[common])
        rows.append(
            {
                "shape": shape,
                "cv_nm": _rms(np.where(measured, cv, np.nan)),
                "crlb_nm": _rms(np.where(measured, bound, np.nan)),
                "brightness_nm": _rms(np.where(measured, bright, np.nan)),
                "coverage": float(measured.sum() / max(common.sum(), 1)),
                "score_nm": molecules,
                "photon_limit_nm": photons,
                "particles_nm": particles,
                "guess_nm": guess,
            }
        )
    return pd.DataFrame(rows).set_index("shape")


def choose(table: pd.DataFrame) -> tuple[str, dict[str, Any]]:
    """The eligible shape with the smallest score (single molecules), or, where no shape's
    photon limit for them is below :data:`GUESS_FRACTION` of a guess, with the smallest error for
    emitters like the calibration particles; and a JSON-able record of why."""
    eligible = table[np.isfinite(table["score_nm"])]
    if eligible.empty:
        raise ValueError(
            "No shape parameter has a usable calibrated range: the particles' images hardly "
            "change through focus (check the z step and that the stack spans focus)."
        )
    limit = GUESS_FRACTION * eligible["guess_nm"].iloc[0]
    blind = bool(eligible["photon_limit_nm"].min() >= limit)
    best = str(eligible["particles_nm" if blind else "score_nm"].idxmin())
    row = eligible.loc[best]
    parts = f"cross-validated {row.cv_nm:.1f} nm, Cramer-Rao {row.crlb_nm:.0f} nm" + (
        f", brightness {row.brightness_nm:.0f} nm" if row.brightness_nm else ""
    )
    if blind:
        reason = (
            f"shape={best!r}: expected sigma_z {row.particles_nm:.0f} nm for emitters like the "
            f"calibration particles (no shape's Cramer-Rao bound for 1000-photon emitters is "
            f"better than {GUESS_FRACTION:.0%} of a guess, {row.guess_nm:.0f} nm; "
            f"{row.photon_limit_nm:.0f} nm here; {parts})"
        )
    else:
        reason = (
            f"shape={best!r}: expected sigma_z {row.score_nm:.0f} nm for 1000-photon emitters "
            f"over {row.coverage:.0%} of the usable range ({parts})"
        )
    scores = {
        name: {k: (v if isinstance(v, str | bool) else float(v)) for k, v in r.items()}
        for name, r in table.astype(object).to_dict("index").items()
    }
    return best, {"chosen": best, "reason": reason, "scores": scores}

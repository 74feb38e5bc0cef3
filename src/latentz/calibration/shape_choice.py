"""Which shape parameter to localize with: the one with the best expected σ_z for single
molecules over the calibrated range (``calibrate(shape=None)``).

Every candidate (``rho``, ``rho_w``, ``rho_A``, ``auto``, ``auto_A``) is judged on the same
planes: those where any candidate measures z well (the union of their
:func:`~latentz.calibration.precision.usable_planes` at 1000 photons) on the usable particles.
On each plane the expected z error is the quadrature sum of three independent errors:

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

Where a candidate cannot measure z (outside its monotonic range) its error is that of a guess
anywhere in the range, span/√12, and no plane counts worse than that. The score is the RMS of
the expected error over the common planes, so a small σ_z over a short range does not win.
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
from latentz.calibration.shape import uses_amplitude
from latentz.calibration.traces import Traces

__all__ = ["BRIGHTNESS_RATIO", "score_shapes", "choose"]

#: Brightness ratio (emitter / calibration particle) the A-normalised shapes are charged for.
BRIGHTNESS_RATIO = 2.0


def _rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2))) if values.size else np.nan


def _cross_validated(local: LocalModels, shape: str, use: np.ndarray, positions: np.ndarray):
    """(n, n_z) z error (nm) of each particle's images localized with the nearest other usable
    particle's inverse model; the local residual σ_z for a lone particle."""
    model = local.shapes[shape]
    rows = np.flatnonzero(use)
    if rows.size < 2:
        return model.sigma_z
    _, nearest = cKDTree(positions[rows]).query(positions[rows], k=2)
    errors = np.full(model.values.shape, np.nan)
    for i, j in zip(rows, rows[nearest[:, 1]], strict=True):
        inverse = model.inverse[np.full(model.values.shape[1], j)]
        s = model.values[i]
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
    does) and ``score_nm`` (the expected z error over the common planes).

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
        parts[shape] = (cv, bound, bright)
        common |= usable_planes(bound) & valid[:, None]
    z = np.where(common, local.z_nm, np.nan)[common.any(axis=1)]  # particles with common planes
    span = np.nanmax(z, axis=1) - np.nanmin(z, axis=1) if common.any() else np.zeros(1)
    guess = float(np.nanmean(span)) / np.sqrt(12.0) if common.any() else np.nan
    rows = []
    for shape, (cv, bound, bright) in parts.items():
        total = np.sqrt(cv**2 + bound**2 + bright**2)
        measured = common & np.isfinite(total)
        expected = np.where(measured, np.minimum(total, guess), guess)[common]
        rows.append(
            {
                "shape": shape,
                "cv_nm": _rms(np.where(measured, cv, np.nan)),
                "crlb_nm": _rms(np.where(measured, bound, np.nan)),
                "brightness_nm": _rms(np.where(measured, bright, np.nan)),
                "coverage": float(measured.sum() / max(common.sum(), 1)),
                "score_nm": _rms(expected),
            }
        )
    return pd.DataFrame(rows).set_index("shape")


def choose(table: pd.DataFrame) -> tuple[str, dict[str, Any]]:
    """The eligible shape with the smallest score, and a JSON-able record of why."""
    eligible = table[np.isfinite(table["score_nm"])]
    if eligible.empty:
        raise ValueError(
            "No shape parameter has a usable calibrated range: the particles' images hardly "
            "change through focus (check the z step and that the stack spans focus)."
        )
    best = str(eligible["score_nm"].idxmin())
    row = eligible.loc[best]
    reason = (
        f"shape={best!r}: expected sigma_z {row.score_nm:.0f} nm for 1000-photon emitters "
        f"over {row.coverage:.0%} of the usable range (cross-validated {row.cv_nm:.1f} nm, "
        f"Cramer-Rao {row.crlb_nm:.0f} nm"
        + (f", brightness {row.brightness_nm:.0f} nm" if row.brightness_nm else "")
        + ")"
    )
    scores = {
        name: {k: (v if isinstance(v, str | bool) else float(v)) for k, v in r.items()}
        for name, r in table.astype(object).to_dict("index").items()
    }
    return best, {"chosen": best, "reason": reason, "scores": scores}

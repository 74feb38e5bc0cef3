"""Culling of defective calibration particles (paper Methods).

Some particles form images that differ systematically from the population: dimers, oversized
particles, debris. They would embed errors in the calibration that are not the field dependence it
models. Each particle is described by a few features, compared with robust statistics
(median and MAD-scaled standard deviation, so that the defects themselves do not inflate the scale)
against the whole population and against its nearest field neighbours (the aberrations change
across the field, so a shape curve is judged against the curves next to it):

========================  =====================================================  ===========
feature                   meaning                                                compared to
========================  =====================================================  ===========
``width_focus``           mean Gaussian width near focus (oversized, dimer)      neighbours
``log_photons``           log of the integrated signal near focus (size, dimer)  population
``curve_rms``             RMS deviation of s(z − z_f) from the neighbours'       population
``z_f_offset``            z_f minus the neighbours' median, after tilt removal   population
========================  =====================================================  ===========

Particles also fail outright: fits that did not converge, never in focus within the stack,
another particle in the ROI, or no monotonic range of the shape parameter. Every particle keeps a
``culled`` flag and a ``cull_reason`` naming every test it failed; none is dropped silently.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.sanity import LatentzWarning
from latentz.calibration.local import LocalModels, row_mean
from latentz.calibration.traces import Traces

__all__ = ["particle_features", "robust_z", "neighbour_offsets", "cull", "FEATURE_TESTS"]

#: feature -> which deviations are defects: "high" (one-sided) or "both"
FEATURE_TESTS = {
    "width_focus": "high",
    "log_photons": "both",
    "curve_rms": "high",
    "z_f_offset": "both",
}


def robust_z(values: np.ndarray, reference: np.ndarray, *, name: str = "values") -> np.ndarray:
    """``(values − median) / (1.4826 MAD)`` with median and MAD over the ``reference`` subset.

    With fewer than 3 finite references the scores are 0 (the criterion ``name`` culls nothing),
    and a :class:`~latentz._shared.sanity.LatentzWarning` says so."""
    ref = values[reference & np.isfinite(values)]
    if ref.size < 3:
        warnings.warn(
            f"Culling by {name} is disabled: {ref.size} reference particle(s) have a finite "
            "value, at least 3 are needed.",
            LatentzWarning,
            stacklevel=2,
        )
        return np.zeros_like(values)
    centre = np.median(ref)
    scale = 1.4826 * np.median(np.abs(ref - centre))
    scale = scale if scale > 0 else np.std(ref) if np.std(ref) > 0 else 1.0
    return (values - centre) / scale


def neighbour_offsets(
    values: np.ndarray, positions: np.ndarray, reference: np.ndarray, *, k: int
) -> np.ndarray:
    """Each value minus the median of its ``k`` nearest ``reference`` neighbours (itself
    excluded). ``values`` is (n,) or (n, m); for (n, m) the median is taken row-wise per column."""
    idx_ref = np.flatnonzero(reference)
    if idx_ref.size < 2:
        warnings.warn(
            f"Neighbour comparison is disabled: {idx_ref.size} reference particle(s), at least "
            "2 are needed.",
            LatentzWarning,
            stacklevel=2,
        )
        return np.zeros_like(values)
    k_use = min(k, idx_ref.size - 1)
    tree = cKDTree(positions[idx_ref])
    _, nn = tree.query(positions, k=k_use + 1)
    nn = idx_ref[np.atleast_2d(nn.reshape(len(positions), -1))]
    self_hit = nn == np.arange(len(positions))[:, None]
    # drop the particle itself (or, when it is not a reference, the farthest neighbour)
    order = np.argsort(self_hit, axis=1, kind="stable")[:, :k_use]
    nn = np.take_along_axis(nn, order, axis=1)
    return values - np.nanmedian(values[nn], axis=1)


def _near_focus(z: np.ndarray, z_f: np.ndarray, values: np.ndarray, half_nm: float) -> np.ndarray:
    near = np.abs(z - z_f[:, None]) <= half_nm
    near |= np.abs(z - z_f[:, None]) <= np.nanmin(np.abs(z - z_f[:, None]), axis=1)[:, None]
    return row_mean(np.where(near, values, np.nan))


def particle_features(
    traces: Traces,
    local: LocalModels,
    shape: str,
    positions_nm: np.ndarray,
    reference: np.ndarray,
    *,
    k: int = 8,
    focus_half_nm: float = 100.0,
    curve_half_nm: float = 1000.0,
    n_grid: int = 41,
) -> pd.DataFrame:
    """The culling features of every particle (see the module docstring).

    ``local`` is on the tilt-corrected axis; ``reference`` marks the particles that may serve as
    neighbours and population (those not failed outright).
    """
    z, z_f = local.z_nm, local.z_f
    wx, wy, rho, amp = traces["wx"], traces["wy"], traces["rho"], traces["amplitude"]
    signal = 2 * np.pi * amp * np.abs(wx * wy) * np.sqrt(np.clip(1 - rho**2, 1e-12, None))
    width = _near_focus(z, z_f, (np.abs(wx) + np.abs(wy)) / 2, focus_half_nm)
    photons = _near_focus(z, z_f, signal, focus_half_nm)
    forward = local.shapes[shape].forward
    offsets = np.linspace(-curve_half_nm, curve_half_nm, n_grid)
    curves = forward(z_f[:, None] + offsets[None, :])
    deviation = neighbour_offsets(curves, positions_nm, reference, k=k)
    spread = np.nanmedian(np.abs(deviation[reference]), axis=0) if reference.any() else 1.0
    curve_rms = np.sqrt(row_mean((deviation / np.where(spread > 0, spread, 1.0)) ** 2))
    features = {
        "width_focus": neighbour_offsets(width, positions_nm, reference, k=k),
        "log_photons": np.log(np.clip(photons, 1e-12, None)),
        "curve_rms": np.log(curve_rms),
        "z_f_offset": neighbour_offsets(z_f, positions_nm, reference, k=k),
    }
    return pd.DataFrame(features)


def cull(
    features: pd.DataFrame,
    hard: dict[str, np.ndarray],
    *,
    threshold: float = 6.0,
) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """Flag the particles to cull.

    Parameters
    ----------
    features : DataFrame
        From :func:`particle_features`.
    hard : dict of str -> bool ndarray (n,)
        Outright failures, by reason.
    threshold : float
        Robust z-score beyond which a feature marks a particle as defective. With Gaussian
        features, 6 robust standard deviations flag about 2e-9 of good particles per feature.

    Returns
    -------
    culled : ndarray of bool (n,)
    reason : ndarray of str (n,)
        Comma-separated reasons ("" when kept).
    scores : DataFrame
        The robust z-score of every feature.
    """
    n = len(features)
    failed = np.zeros(n, bool)
    for mask in hard.values():
        failed |= np.asarray(mask, bool)
    scores = pd.DataFrame(
        {name: robust_z(features[name].to_numpy(), ~failed, name=name) for name in features.columns}
    )
    flags: dict[str, Any] = dict(hard)
    for name, side in FEATURE_TESTS.items():
        if name not in scores:
            continue
        score = scores[name].to_numpy()
        with np.errstate(invalid="ignore"):
            bad = score > threshold if side == "high" else np.abs(score) > threshold
        flags[name] = bad | (~np.isfinite(score) & ~failed)
    reason = np.array(
        [",".join(name for name, mask in flags.items() if mask[i]) for i in range(n)], dtype=object
    )
    culled = reason != ""
    return culled, reason, scores

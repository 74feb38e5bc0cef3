"""Each calibration particle's own height above the substrate, from its brightness.

A bead lies on the substrate with its centre d/2 above it, so beads of unequal size come to best
focus at unequal stage positions even where the optics are the same: the paper's 1 µm beads
(24 nm s.d.) scatter by 12 nm. Each particle's local models carry that offset; the ``nearest``
field model hands it to every spot near the particle, and the cross-validation counts it as field
error, because the held-out particle's own curve is the truth it is compared with.

A bead dyed through its volume emits in proportion to d³ (through its surface, d²), so for a
small spread of sizes its height offset is linear in the log of its brightness N:
δ ≈ (d̄ / 2p) ln(N / N̄), p = 3 (or 2). The slope k is not assumed but fitted to the kept
particles' best focus z_f, jointly with a smooth surface of best focus: a polynomial in field
position of degree up to 3 (no more terms than a quarter of the particles), which takes up the
tilt, the field curvature and the illumination's fall-off, so that these do not pass for a
relation between brightness and focus. N is the median of the fitted photons over the planes
nearest each particle's focus, less its smooth trend across the field (the same polynomial: the
illumination, and the share of an aberrated spot that a Gaussian holds, vary with field position
and are no bead's size). Where k is significant (two-sided p below :data:`P_VALUE`, t
distribution) and plausible (the beads it implies, at least 4|k| across, are no wider than
:data:`MAX_DIAMETER_PER_FWHM` times their in-focus images), each kept particle's δ = k × that
brightness residual is taken off its models,
which puts every particle at the height of a bead of the brightness typical at its place;
otherwise nothing moves. Beads of one size, or brightness that varies for other reasons
(labelling), leave k insignificant.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats

from latentz.fit._model import photons_of

__all__ = ["particle_heights", "describe", "P_VALUE", "MIN_PARTICLES", "MAX_DIAMETER_PER_FWHM"]

#: Significance below which the fitted slope is applied (two-sided).
P_VALUE = 1e-3
#: Fewest kept particles for the fit: a plane of focus, the slope, and 4 degrees of freedom.
MIN_PARTICLES = 8
#: Planes nearest each particle's best focus whose median photons are its brightness.
_FOCUS_PLANES = 7
#: Largest bead diameter, in FWHM of the beads' own in-focus images, that a slope may imply:
#: a bead imaged in focus is at least about 0.7 times its diameter wide. A slope k implies
#: beads of diameter 2pk, at least 4|k|; a steeper one is the field's (aberrations that change
#: both the Gaussian's share of the light and the focus, beyond the polynomial), not a size.
MAX_DIAMETER_PER_FWHM = 1.5
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def _at_focus(values: np.ndarray, z_nm: np.ndarray, z_f: np.ndarray) -> np.ndarray:
    """Median of each row of ``values`` (n, n_z) over its :data:`_FOCUS_PLANES` usable (finite,
    positive) planes nearest its best focus ``z_f`` (``z_nm`` (n, n_z), nm); NaN for a row with
    none, without a numpy warning."""
    usable = np.isfinite(values) & (values > 0)
    out = np.full(len(z_f), np.nan)
    rows = usable.any(axis=1) & np.isfinite(z_f)
    distance = np.where(usable[rows], np.abs(z_nm[rows] - z_f[rows, None]), np.inf)
    nearest = np.argsort(distance, axis=1)[:, :_FOCUS_PLANES]
    chosen = np.take_along_axis(np.where(usable[rows], values[rows], np.nan), nearest, axis=1)
    out[rows] = np.nanmedian(chosen, axis=1)
    return out


def brightness(traces: Any, z_nm: np.ndarray, z_f: np.ndarray) -> np.ndarray:
    """ln of each particle's photons near its best focus (the fitted Gaussian's integral,
    :func:`_at_focus`)."""
    photons = photons_of(traces["amplitude"], traces["wx"], traces["wy"], traces["rho"])
    return np.log(_at_focus(photons, z_nm, z_f))


def _surface(position_px: np.ndarray, degree: int) -> np.ndarray:
    """(n, terms) monomials x^i y^j, i + j <= ``degree``, of positions scaled to [-1, 1]."""
    centred = position_px - position_px.mean(axis=0)
    u = centred / max(float(np.max(np.abs(centred))), 1e-12)
    return np.column_stack(
        [u[:, 0] ** i * u[:, 1] ** j for i in range(degree + 1) for j in range(degree + 1 - i)]
    )


def particle_heights(
    traces: Any,
    z_nm: np.ndarray,
    z_f: np.ndarray,
    position_px: np.ndarray,
    kept: np.ndarray,
    *,
    pixel_size_nm: float,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Each particle's own height offset δ (nm; zero where not applied) and the fit's summary.

    ``z_nm`` (n, n_z) and ``z_f`` (n,) are on the piezo axis, ``position_px`` (n, 2) in field
    pixels, ``kept`` (n,) the particles to fit and to move. The summary holds ``slope_nm`` (k,
    nm per e-fold of brightness), ``slope_err_nm``, ``p_value``, ``particles`` (used),
    ``implied_diameter_nm`` (4|k|) and ``max_diameter_nm`` (:data:`MAX_DIAMETER_PER_FWHM` times
    the median in-focus FWHM), ``applied`` (significant and plausible), ``rms_nm`` (of the δ
    applied) and, where applied, ``heights_nm`` (δ, a list).
    """
    n = len(z_f)
    heights = np.zeros(n)
    log_n = brightness(traces, z_nm, z_f)
    use = np.asarray(kept, bool) & np.isfinite(log_n) & np.isfinite(z_f)
    m = int(use.sum())
    summary: dict[str, Any] = {"slope_nm": float("nan"), "slope_err_nm": float("nan"),
                               "p_value": float("nan"), "particles": m, "applied": False,
                               "rms_nm": 0.0}  # fmt: skip
    if m < MIN_PARTICLES:
        return heights, summary
    degree = max(d for d in (1, 2, 3) if (d + 1) * (d + 2) // 2 <= max(m // 4, 3))
    surface = _surface(position_px[use], degree)
    # the brightness beyond its smooth trend across the field (illumination, and the share of
    # an aberrated spot that a Gaussian holds): the slope and the heights are of that part only
    own = log_n[use] - surface @ np.linalg.lstsq(surface, log_n[use], rcond=None)[0]
    design = np.column_stack([surface, own])
    coef, *_ = np.linalg.lstsq(design, z_f[use], rcond=None)
    resid = z_f[use] - design @ coef
    dof = m - design.shape[1]
    scale = float(resid @ resid) / dof
    gram = design.T @ design
    if np.linalg.cond(gram) > 1e12 or scale <= 0:  # collinear particles, or an exact fit
        return heights, summary
    err = float(np.sqrt(scale * np.linalg.inv(gram)[-1, -1]))
    slope = float(coef[-1])
    p = float(2 * stats.t.sf(abs(slope) / err, dof))
    width_px = _at_focus(np.sqrt(np.abs(traces["wx"] * traces["wy"])), z_nm, z_f)[use]
    largest = MAX_DIAMETER_PER_FWHM * _FWHM_PER_SIGMA * pixel_size_nm * np.nanmedian(width_px)
    implied = 4 * abs(slope)  # the diameter of surface-dyed beads; 6|k| if dyed throughout
    summary.update(slope_nm=slope, slope_err_nm=err, p_value=p, implied_diameter_nm=implied,
                   max_diameter_nm=float(largest),
                   applied=bool(p < P_VALUE and implied <= largest))  # fmt: skip
    if summary["applied"]:
        heights[use] = slope * own
        summary["rms_nm"] = float(np.sqrt(np.mean(heights[use] ** 2)))
        summary["heights_nm"] = [round(float(h), 3) for h in heights]  # 1 pm: a small attribute
    return heights, summary


def describe(summary: dict[str, Any] | None) -> str:
    """One sentence on the particles' heights for reports (``summary`` from
    :func:`particle_heights`, as ``cal.options["particle_heights"]``; None: not fitted)."""
    if not summary or "slope_nm" not in summary:
        return "Particle heights: not corrected (heights=False, or a calibration from before)."
    if not np.isfinite(summary["slope_nm"]):
        return (f"Particle heights: not corrected ({summary['particles']} kept particles; the "
                f"fit against brightness needs {MIN_PARTICLES}).")  # fmt: skip
    slope = f"{summary['slope_nm']:+.0f} ± {summary['slope_err_nm']:.0f} nm per e-fold"
    if summary["applied"]:
        return (f"Particle heights: best focus moves {slope} of brightness (p = "
                f"{summary['p_value']:.1e}), as beads of unequal size do; each particle's models "
                f"were moved by its own height, {summary['rms_nm']:.1f} nm RMS.")  # fmt: skip
    if summary["p_value"] < P_VALUE:
        return (f"Particle heights: best focus follows brightness ({slope}, p = "
                f"{summary['p_value']:.1e}), but that implies beads at least "
                f"{summary['implied_diameter_nm']:.0f} nm wide, more than their in-focus images "
                f"allow ({summary['max_diameter_nm']:.0f} nm): the field's structure, not the "
                f"beads' size; no particle moved.")  # fmt: skip
    return (f"Particle heights: best focus does not follow brightness ({slope}, p = "
            f"{summary['p_value']:.2f}); no particle moved.")  # fmt: skip

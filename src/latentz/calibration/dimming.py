"""The shape and place a dimmer emitter shows: the photon-dependent bias of the Gaussian fit.

A Gaussian fitted to a PSF that is not a Gaussian converges to the Gaussian nearest the PSF *under
the fit's weights* ``1 / (mu + b + readnoise²)``. On a bright calibration particle the weights
follow the spot, and its core dominates; on a dim emitter over the same background they are nearly
uniform, and the wings count as much as the core. So the same PSF gives other widths and ρ, and
another shape value s, at other brightness: a bias of z that no covariance holds (58–65 nm RMS
below 1500 photons on the validation microscope, ``docs/accuracy.md``).

It is predictable from the calibration's own images. For a noise-free image ``f·S + b`` (PSF S,
scale f, background b) the maximum-likelihood fit's widths and ρ depend on f and b only through
the ratio ``c = (b + readnoise²) / A`` of background (and read-noise variance) to the spot's peak
amplitude A: scaling data and model by f leaves the score equations unchanged. So each
calibration ROI is refitted with ``c·Â`` more background (:data:`LEVELS`; Â its fitted
amplitude) and no read noise, which is the particle's PSF seen as a dimmer emitter (its own
background is kept, not subtracted: the fitted background of a bright image also holds the
PSF's far wings, and removing it would cut them off); the calibration's noise stays ~0.5 % of
the peak. Each refit's c is measured as a spot's is, from its own fitted background and
amplitude. :meth:`Calibration.apply <latentz.calibration.Calibration.apply>` interpolates these
fits at each spot's own c (log c, between the calibration's own c and the levels) and plane, and
removes the difference of their shape value from the calibration's from the spot's s before z is
found (:func:`shape_shift`).

Where the calibration particles' brightness follows their size (beads of unequal size, whose
heights :mod:`latentz.calibration.heights` found and took off), spots within the calibration's
own range of brightness are not corrected. Within that range a spot's brightness differs from
its nearest particle's mostly by its size, and a smaller bead is not a dimmer copy of the same
PSF: its image is narrower too. Correcting it there added error (latentz's simulator, beads as
bright as the calibration's, of 24 nm diameter s.d.: z 18.63 nm RMS without the correction,
18.78 with it from each particle's own c, 18.65 from the edge). So the shift starts at the
:func:`dimmest` ratio at the spot's depth, and its start moves back to the particle's own c as
the spot goes as far again beyond that edge (in log c): emitters many times dimmer than the
calibration, which the correction is for, get all of it. Where the particles are of one size,
their brightness differs by illumination and by the PSF's peak at their place, which is what the
correction models, and every spot is corrected from its particle's own c: on the validation
microscope's beads of one size, starting at the edge had cost `curves` 0.5 nm of z (20.6 →
21.1 nm RMS, full size, test emitters of 2·10⁴ and 2·10⁵ photons).

The same refits hold the position's bias. A PSF that is not symmetric about its centre (coma)
puts more light in one wing; where the wings weigh more, the fitted centre moves towards that
wing, by 0.1–0.26 px (13–34 nm) between 2·10⁵ and 800–3000 photons for 30 nm RMS of coma at
NA 1.0 (``tests/calibration/test_dimming.py``). The calibration's Δx'(z), Δy'(z) hold the
bright particles' centres, so each refit's position less the calibration's own fit
(``dim{k}_dx``, ``dim{k}_dy``) is interpolated in log c as the shape value is
(:func:`position_shift`) and taken off the spot's position with Δx', Δy'.

What it cannot see: a calibration bead is not a point emitter, unless the calibration was given
the beads' diameter (docs/accuracy.md, "Emitters of another size than the calibration
particles"), and at very low counts the fit's own small-sample bias.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import pandas as pd

__all__ = [
    "LEVELS", "DIM_COLUMNS", "SHAPE_DIM_COLUMNS", "EDGE_QUANTILE", "Levels", "background_ratio",
    "dim_fits", "dimmest", "level_positions", "level_shift", "level_value", "levels",
    "position_shift", "shape_levels", "shape_shift",
]  # fmt: skip

#: Background-to-peak ratios c = (b + readnoise²) / A at which the calibration ROIs are refitted:
#: a single molecule of 10³–10⁴ photons (A ≈ 30–700 per px) over 10–100 photons per px spans
#: c ≈ 0.02–3.
LEVELS = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
_FITTED = ("amplitude", "wx", "wy", "rho")
#: The calibration's range of brightness ends at this quantile of its particles' background
#: ratios c at each depth (:func:`dimmest`); where brightness follows particle size, spots
#: within it are not corrected (module notes).
EDGE_QUANTILE = 0.95
#: Trace names of the refits: ``dim{k}_{amplitude, wx, wy, rho, background}`` for level k, and
#: ``dim{k}_dx``, ``dim{k}_dy``, the refit's position less the calibration's own fit's (px).
DIM_COLUMNS = tuple(
    f"dim{k}_{name}" for k in range(len(LEVELS)) for name in (*_FITTED, "background", "dx", "dy")
)
#: The refits the shape's correction reads (files older than ``dim{k}_dx`` hold only these).
SHAPE_DIM_COLUMNS = tuple(name for name in DIM_COLUMNS if not name.endswith(("_dx", "_dy")))


def dim_fits(
    rois: np.ndarray, params: np.ndarray, *, method: str, device: str = "auto"
) -> dict[str, np.ndarray]:
    """Refits (:data:`DIM_COLUMNS`, each (n,)) of calibration ROIs ``rois`` (n, h, w,
    photoelectrons) fitted as ``params`` (n, 7, natural) over ``c·Â`` more background for each
    c of :data:`LEVELS` (module notes). NaN where the fit is not usable."""
    from latentz.fit import PARAMS, fit_arrays

    amplitude = params[:, 2]
    ok = np.all(np.isfinite(params), axis=1) & (amplitude > 0)
    out = {}
    for k, level in enumerate(LEVELS):
        added = np.where(ok, level * amplitude, 0.0)
        start = params.copy()
        start[:, 3] += added
        fit = fit_arrays(rois + added[:, None, None], method=method, init=start, device=device,
                         errors="crlb")  # fmt: skip
        usable = ok & fit.converged
        for name in (*_FITTED, "background"):
            value = fit.params[:, PARAMS.index(name)]
            out[f"dim{k}_{name}"] = np.where(usable, value, np.nan)
        for axis in ("x", "y"):
            shift = fit.params[:, PARAMS.index(axis)] - params[:, PARAMS.index(axis)]
            out[f"dim{k}_d{axis}"] = np.where(usable, shift, np.nan)
    return out


def background_ratio(background: np.ndarray, amplitude: np.ndarray, readnoise: float) -> np.ndarray:
    """c = (b + readnoise²) / A of fits of background ``background`` and peak ``amplitude``
    (photoelectrons per pixel); NaN or inf, without a numpy warning, where A is 0 or NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return (np.asarray(background, float) + readnoise**2) / np.asarray(amplitude, float)


def dimmest(z_nm: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The calibration's dimmest background ratio at each depth: the :data:`EDGE_QUANTILE` of
    ``c`` (n, m; the kept particles' (b + readnoise²) / A on their planes at ``z_nm``, (n, m)
    nm, each row the same planes shifted by its particle's focus) over particles, pooled in
    bins one plane spacing wide centred on the median row's planes. Returns the bins' centres
    (nm) and that ratio, where a bin holds any finite value."""
    step = float(np.nanmedian(np.diff(z_nm, axis=1)))
    ok = np.isfinite(z_nm) & np.isfinite(c)
    start = float(np.nanmedian(z_nm[:, 0]))
    bins = np.rint((z_nm[ok] - start) / step).astype(int)
    edge = pd.Series(c[ok]).groupby(bins).quantile(EDGE_QUANTILE)
    return start + step * edge.index.to_numpy(float), edge.to_numpy(float)


def shape_shift(
    shape_of: Callable[..., np.ndarray],
    traces_at: Callable[[str], np.ndarray],
    c_spot: np.ndarray,
    c_own: np.ndarray,
    c_from: np.ndarray | None = None,
) -> np.ndarray:
    """Bias (n,) of the shape value of spots of background ratio ``c_spot`` against the
    calibration's own fit (ratio ``c_own``): ``s(c_spot) − s(c_from)`` (:func:`level_shift`).

    ``traces_at(name)`` gives a trace at each spot's particle and plane ((n,); name one of
    :data:`DIM_COLUMNS`, or "amplitude", "wx", "wy", "rho" for the calibration's own fit), and
    ``shape_of(amplitude, wx, wy, rho)`` the shape value, or m values (n, m) whose biases
    (n, m) are returned at once.
    """
    return level_shift(shape_levels(shape_of, traces_at, c_own), c_spot, c_from)


def shape_levels(
    shape_of: Callable[..., np.ndarray],
    traces_at: Callable[[str], np.ndarray],
    c_own: np.ndarray,
) -> Levels:
    """The shape value (or m values) of :func:`shape_shift`'s ``shape_of`` over log c at each of
    n particles' planes (:func:`levels`; ``traces_at`` and ``c_own`` as :func:`shape_shift`'s)."""
    own = shape_of(*(traces_at(name) for name in _FITTED))
    dim = [shape_of(*(traces_at(f"dim{k}_{name}") for name in _FITTED)) for k in range(len(LEVELS))]
    return levels(own, dim, traces_at, c_own)


def position_shift(
    traces_at: Callable[[str], np.ndarray],
    c_spot: np.ndarray,
    c_own: np.ndarray,
    c_from: np.ndarray | None = None,
) -> np.ndarray:
    """Bias (n, 2; px) of the fitted x and y positions of spots of background ratio ``c_spot``
    against the calibration's own fit (ratio ``c_own``), from the refits' shifts
    ``dim{k}_dx``, ``dim{k}_dy`` (:func:`level_shift`; ``traces_at`` as :func:`shape_shift`'s).
    A PSF that is not symmetric (coma) puts its far wing on one side: where the wings weigh
    more, the Gaussian's centre moves towards them."""
    own = np.zeros((np.size(c_spot), 2))
    dim = [
        np.column_stack([traces_at(f"dim{k}_dx"), traces_at(f"dim{k}_dy")])
        for k in range(len(LEVELS))
    ]
    return level_shift(levels(own, dim, traces_at, c_own), c_spot, c_from)


class Levels(NamedTuple):
    """A value v (or m values) over log c at n particles' planes (:func:`levels`): ``start``
    (n,), log of the calibration's own c; ``knots`` (n, levels + 1), ascending log c from
    ``start``; ``values`` (n, levels + 1[, m]), v there."""

    start: np.ndarray
    knots: np.ndarray
    values: np.ndarray


def levels(
    own: np.ndarray,
    dim: list[np.ndarray],
    traces_at: Callable[[str], np.ndarray],
    c_own: np.ndarray,
) -> Levels:
    """v(c) of a value v (or m values) whose calibration fit (ratio ``c_own``) gives ``own`` (n,)
    or (n, m) and whose refits give ``dim`` (one array like ``own`` per level of
    :data:`LEVELS`): linear in log c between the calibration's own fit and the refits above
    ``c_own`` (the last one's beyond them; NaN where a refit is missing). A refit's own c is
    measured as a spot's: its fitted background over its fitted amplitude (``traces_at``'s
    ``dim{k}_background`` and ``dim{k}_amplitude``; the refit has no read noise). Both differ
    from the level: the fitted background of the bright image also holds the PSF's far wings,
    which are removed with it, and the Gaussian's amplitude changes with the background."""
    with np.errstate(invalid="ignore", divide="ignore"):
        start = np.log(np.asarray(c_own, dtype=np.float64))
        # each refit's own c, measured as a spot's is: its fitted background over its amplitude
        level = np.log(np.column_stack([
            traces_at(f"dim{k}_background") / traces_at(f"dim{k}_amplitude")
            for k in range(len(LEVELS))
        ]))  # fmt: skip
    brighter = ~(level > start[:, None])  # levels the calibration is dimmer than (or unknown)
    knots = np.column_stack([start, np.where(brighter, start[:, None], level)])
    knots = np.maximum.accumulate(knots, axis=1)  # an unknown level between known ones
    own = np.asarray(own, dtype=np.float64)
    trailing = (1,) * (own.ndim - 1)  # the m values of each spot share its knots
    values = np.stack([own, *dim], axis=1)  # (n, levels + 1[, m])
    values[:, 1:] = np.where(brighter.reshape(brighter.shape + trailing), own[:, None],
                             values[:, 1:])  # fmt: skip
    return Levels(start, knots, values)


def level_shift(table: Levels, c_spot: np.ndarray, c_from: np.ndarray | None = None) -> np.ndarray:
    """``v(c_spot) − v(c_from)`` (n,) or (n, m) of the value(s) of ``table`` (:func:`levels`).
    ``c_from`` (default the calibration's own c; never below it) is where the correction
    starts: 0 where ``c_spot ≤ c_from``."""
    x, x_from = level_positions(table.start, c_spot, c_from)
    return level_value(table, x) - level_value(table, x_from)


def level_positions(start: np.ndarray, c_spot: np.ndarray,
                    c_from: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """log c of the spots (n,) and of where their correction starts (:func:`level_shift`), from
    their ``start`` (n,; :class:`Levels`' log of the calibration's own c)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        x_from = start
        if c_from is not None:
            x_from = np.maximum(np.log(np.asarray(c_from, float)), x_from)
        x = np.maximum(np.log(np.asarray(c_spot, dtype=np.float64)), x_from)
    return x, x_from


def level_value(table: Levels, at: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """v (n,) or (n, m) of the value(s) of ``table`` (:func:`levels`) at log c ``at`` (n,):
    linear between its knots, their first and last values beyond them. ``rows`` (n,): the
    table's entries read (default all of them)."""
    n_knots = table.knots.shape[1]
    knots = table.knots if rows is None else table.knots[rows]
    first = n_knots * (np.arange(len(at)) if rows is None else rows)  # flat index of knot 0
    flat_knots = table.knots.ravel()
    flat_values = table.values.reshape((-1, *table.values.shape[2:]))
    j = np.sum(knots[:, 1:] < at[:, None], axis=1)  # knots[j] < at <= knots[j + 1]
    lower = first + j
    upper = first + np.minimum(j + 1, n_knots - 1)
    width = flat_knots[upper] - flat_knots[lower]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(width > 0, (at - flat_knots[lower]) / width, 1.0)
    t = np.clip(t, 0.0, 1.0).reshape(t.shape + (1,) * (table.values.ndim - 2))
    return flat_values[lower] + t * (flat_values[upper] - flat_values[lower])

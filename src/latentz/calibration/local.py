"""Local (per-particle) calibration models (paper Fig. 2, Supp. Table 2).

For every calibration particle, as arrays over all particles at once:

- z_f, the peak of a polynomial (order 5) fitted to A(z) around its maximum (the midpoint of
  the two line foci where A peaks at both);
- Δx'(z) = x'(z) − x'(z_f) and Δy'(z), polynomials of order 16 (eqs. 2–3);
- for each shape parameter s: the forward model s(z) (order 16), the range of z around focus over
  which it is monotonic, and the inverse z(s) (order 16) fitted over that range;
- uncertainties σ_Δx'(z), σ_Δy'(z) and σ_z(z) from the residuals of those fits: the RMS of the
  residuals in a sliding window of z (Fig. 2, bottom panels), corrected for the degrees of freedom
  the polynomial used.

All z models are in piezo coordinates here; :meth:`LocalModels.shifted` moves them onto the
tilt-corrected axis (``z − plane(x, y)``) exactly, by shifting each polynomial's domain.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from latentz.calibration.polymodel import PolyModel
from latentz.calibration.shape import reference_amplitude, shape_value, uses_amplitude
from latentz.calibration.traces import Traces

__all__ = [
    "LocalOptions",
    "best_focus",
    "focus_depth_nm",
    "ShapeModel",
    "LocalModels",
    "fit_local",
    "measured_run",
    "sliding_rms",
    "peak",
    "row_mean",
]


#: A trace's A(z) has two peaks where its running mean dips this much (relative to the lower of
#: the highest values on either side) within the focus window; amplitude noise of bright
#: particles is under 1 %.
DIP_FRACTION = 0.03


@dataclass(frozen=True)
class LocalOptions:
    """Orders and windows of the local models (the paper's orders are the defaults).

    Attributes
    ----------
    amplitude_order : int
        Order of the A(z) polynomial whose peak is z_f (paper: 5).
    focus_fraction : float
        A(z) is fitted on the contiguous planes around its maximum where A ≥ this fraction of the
        maximum, so that the order-5 polynomial describes the peak rather than the tails.
    lateral_order : int
        Order of Δx'(z), Δy'(z) (paper: 16).
    shape_order : int
        Order of the forward s(z) and inverse z(s) models (paper: 16).
    sigma_window_nm : float
        Width of the sliding window for the residual RMS, nm.
    min_range_nm : float
        Shortest monotonic range accepted for an inverse model, nm.
    """

    amplitude_order: int = 5
    focus_fraction: float = 0.6
    lateral_order: int = 16
    shape_order: int = 16
    sigma_window_nm: float = 500.0
    min_range_nm: float = 300.0


@dataclass(frozen=True, eq=False)
class ShapeModel:
    """Local models of one shape parameter for ``n`` particles.

    Attributes
    ----------
    values : ndarray (n, n_z)
        Measured shape values of the calibration images.
    forward : PolyModel
        s(z) over the whole stack.
    inverse : PolyModel
        z(s) over the monotonic range; its domain is the shape range it covers.
    z_range : ndarray (n, 2)
        Monotonic z range (nm) around focus.
    sigma_z : ndarray (n, n_z)
        σ_z at each plane from the inverse model's residuals, nm (NaN outside the range).
    amplitude_ref : ndarray (n,)
        A_{ρ=ρ0} for the A-normalised parameters (NaN otherwise).
    """

    values: np.ndarray
    forward: PolyModel
    inverse: PolyModel
    z_range: np.ndarray
    sigma_z: np.ndarray
    amplitude_ref: np.ndarray

    def shifted(self, dz: np.ndarray) -> ShapeModel:
        """Move onto the axis ``z − dz`` (dz of shape (n,), nm)."""
        forward = PolyModel(self.forward.coef, self.forward.domain - dz[:, None])
        return replace(
            self,
            forward=forward,
            inverse=self.inverse.shifted(dz),
            z_range=self.z_range - dz[:, None],
        )


@dataclass(frozen=True, eq=False)
class LocalModels:
    """All local models of ``n`` calibration particles.

    ``z_nm`` (n, n_z) is each particle's z of each plane on the models' axis (piezo z, or
    tilt-corrected after :meth:`shifted`).
    """

    z_nm: np.ndarray
    z_f: np.ndarray
    in_focus: np.ndarray
    amplitude: PolyModel
    dx: PolyModel
    dy: PolyModel
    sigma_dx: np.ndarray
    sigma_dy: np.ndarray
    shapes: dict[str, ShapeModel]
    theta: float | None

    def shifted(self, dz: np.ndarray) -> LocalModels:
        """Every model moved onto the axis ``z − dz`` (dz of shape (n,), nm)."""
        dz = np.asarray(dz, dtype=np.float64)

        def move(model: PolyModel) -> PolyModel:
            return PolyModel(model.coef, model.domain - dz[:, None])

        return replace(
            self,
            z_nm=self.z_nm - dz[:, None],
            z_f=self.z_f - dz,
            amplitude=move(self.amplitude),
            dx=move(self.dx),
            dy=move(self.dy),
            shapes={k: v.shifted(dz) for k, v in self.shapes.items()},
        )


def row_mean(values: np.ndarray) -> np.ndarray:
    """Mean of the finite values of each row (NaN for a row without any), without warnings."""
    finite = np.isfinite(values)
    count = finite.sum(axis=1)
    total = np.where(finite, values, 0.0).sum(axis=1)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def sliding_rms(z: np.ndarray, residuals: np.ndarray, *, window_nm: float, n_params: int):
    """RMS of ``residuals`` (n, n_z) in a sliding window of ``window_nm`` centred on each plane.

    NaN residuals are ignored. The result is scaled by ``sqrt(m / (m − n_params))`` with ``m`` the
    particle's number of residuals, the usual correction for the parameters the fit used. Planes
    without residuals get NaN.
    """
    valid = np.isfinite(residuals)
    sq = np.where(valid, residuals, 0.0) ** 2
    near = (np.abs(z[:, :, None] - z[:, None, :]) <= window_nm / 2).astype(np.float64)
    total = np.einsum("nk,njk->nj", sq, near)
    count = np.einsum("nk,njk->nj", valid.astype(np.float64), near)
    m = valid.sum(axis=1, keepdims=True).astype(np.float64)
    dof = np.sqrt(m / np.maximum(m - n_params, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(total / count) * dof
    return np.where(valid, rms, np.nan)


def peak(model: PolyModel, *, n_grid: int = 801) -> tuple[np.ndarray, np.ndarray]:
    """Position of each model's maximum inside its domain, and whether it is interior.

    The maximum on a grid of ``n_grid`` points is refined by a parabola through its neighbours.
    """
    lo, hi = model.domain[:, 0], model.domain[:, 1]
    u = np.linspace(0.0, 1.0, n_grid)
    grid = lo[:, None] + (hi - lo)[:, None] * u
    values = model(grid)
    i = np.argmax(np.where(np.isfinite(values), values, -np.inf), axis=1)
    interior = (i > 0) & (i < n_grid - 1) & model.valid
    j = np.clip(i, 1, n_grid - 2)
    rows = np.arange(len(model))
    y0, y1, y2 = values[rows, j - 1], values[rows, j], values[rows, j + 1]
    denom = y0 - 2 * y1 + y2
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(denom < 0, 0.5 * (y0 - y2) / denom, 0.0)
    step = (hi - lo) / (n_grid - 1)
    return grid[rows, j] + np.clip(frac, -1, 1) * step, interior


def _focus_window(z: np.ndarray, amp: np.ndarray, fraction: float, min_planes: int) -> np.ndarray:
    """Contiguous planes around each trace's maximum where A ≥ fraction × max (at least
    ``min_planes`` of them)."""
    n, n_z = amp.shape
    filled = np.where(np.isfinite(amp), amp, -np.inf)
    top = np.argmax(filled, axis=1)
    below = filled < fraction * filled[np.arange(n), top][:, None]
    left, right = _run_bounds(below, top)
    half = (min_planes + 1) // 2
    left = np.minimum(left, np.maximum(top - half, 0))
    right = np.maximum(right, np.minimum(top + half, n_z - 1))
    return _between(left, right, n_z) & np.isfinite(amp)


def focus_depth_nm(z: np.ndarray, amplitude: np.ndarray, fraction: float) -> np.ndarray:
    """Half the z extent (nm, (n,)) of the contiguous planes about each trace's maximum where
    its amplitude A (n, n_z) is at least ``fraction`` of that maximum; ``z`` (n, n_z) nm."""
    window = _focus_window(z, amplitude, fraction, 1)
    inside = np.where(window, z, np.nan)
    with np.errstate(invalid="ignore"):
        return (np.fmax.reduce(inside, axis=1) - np.fmin.reduce(inside, axis=1)) / 2


def _run_bounds(breaks: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last plane (n,) of the run about each row's plane ``centre`` that no break of
    ``breaks`` (n, n_z) interrupts; the centre plane always belongs to it."""
    n_z = breaks.shape[1]
    idx = np.arange(n_z)
    left = np.max(np.where(breaks & (idx < centre[:, None]), idx, -1), axis=1) + 1
    right = np.min(np.where(breaks & (idx > centre[:, None]), idx, n_z), axis=1) - 1
    return left, right


def _plane_of(z: np.ndarray, z_f: np.ndarray) -> np.ndarray:
    """Index (n,) of each particle's plane nearest its focus z_f (the first plane where z_f is
    NaN)."""
    return np.argmin(np.abs(z - np.nan_to_num(z_f)[:, None]), axis=1)


def _between(left: np.ndarray, right: np.ndarray, n_z: int) -> np.ndarray:
    """(n, n_z) mask of the planes from ``left`` to ``right`` inclusive."""
    idx = np.arange(n_z)
    return (idx >= left[:, None]) & (idx <= right[:, None])


def measured_run(traces: Traces, z: np.ndarray, z_f: np.ndarray) -> np.ndarray:
    """(n, n_z) mask of the planes each particle's models may use: the run about its focus
    with no two consecutive planes unmeasured (a failed fit's NaN). A polynomial over a wider
    gap is unconstrained there, and a plane beyond it would let the models reach across."""
    measured = np.logical_and.reduce(
        [np.isfinite(traces[c]) for c in ("x", "y", "wx", "wy", "rho", "amplitude")]
    )
    gap = ~measured
    pair = np.zeros_like(gap)
    pair[:, :-1] = gap[:, :-1] & gap[:, 1:]
    pair[:, 1:] |= pair[:, :-1].copy()
    return _between(*_run_bounds(pair, _plane_of(z, z_f)), z.shape[1])


def _monotonic_range(
    forward: PolyModel, z: np.ndarray, z_f: np.ndarray, run: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The run of planes around focus over which s(z) is monotonic, within the measured
    ``run``, as a (n, n_z) mask and a (n, 2) z range. The run is the one containing z_f; its
    ends are where the sign of the model's derivative on the planes changes."""
    rows = np.arange(z.shape[0])
    slope = np.sign(forward.derivative()(z))
    centre = _plane_of(z, z_f)
    left, right = _run_bounds((slope != slope[rows, centre][:, None]) | ~run, centre)
    return _between(left, right, z.shape[1]), np.stack([z[rows, left], z[rows, right]], axis=1)


def _shape_model(
    values: np.ndarray,
    z: np.ndarray,
    z_f: np.ndarray,
    amplitude_ref: np.ndarray,
    options: LocalOptions,
    run: np.ndarray,
) -> ShapeModel:
    order = options.shape_order
    forward = PolyModel.from_estimate(z, values, order=order, mask=run)
    mask, z_range = _monotonic_range(forward, z, z_f, run)
    long_enough = (z_range[:, 1] - z_range[:, 0]) >= options.min_range_nm
    ends = forward(z_range)
    s_domain = np.sort(ends, axis=1)
    use = mask & np.isfinite(values) & long_enough[:, None]
    inverse = PolyModel.from_estimate(values, z, order=order, mask=use, domain=s_domain)
    residuals = np.where(use, inverse.residuals(values, z), np.nan)
    sigma = sliding_rms(z, residuals, window_nm=options.sigma_window_nm, n_params=order + 1)
    z_range = np.where(inverse.valid[:, None], z_range, np.nan)
    return ShapeModel(values, forward, inverse, z_range, sigma, amplitude_ref)


def best_focus(
    z_nm: np.ndarray, amplitude: np.ndarray, options: LocalOptions = LocalOptions()
) -> tuple[PolyModel, np.ndarray, np.ndarray]:
    """Best focus z_f (nm, on ``z_nm``'s axis) of each trace: the peak of the order
    ``amplitude_order`` polynomial A(z) fitted around the amplitude's maximum (paper Fig. 2d).

    ``z_nm`` and ``amplitude`` are (n, n_z); NaN amplitudes are ignored. Returns the A(z) models,
    z_f, and whether each peak lies inside its fitting window. The polynomial is fitted on the
    contiguous planes where A ≥ ``focus_fraction`` × max, then again on a window of the same width
    centred on that first peak: on a discrete plane grid the first window is asymmetric about the
    peak, which biases it. This is the definition of best focus that every z of latentz refers to.

    Under astigmatism strong enough that A(z) peaks at both line foci, with a dip between of
    more than :data:`DIP_FRACTION` (:func:`_dip_depth`), the window about the maximum spans
    both, and the polynomial's peak falls at its edge or at either focus, as noise and the field
    favour. There z_f is the midpoint of the two foci, each the peak of A fitted about its own
    maximum down to the dip (:func:`_peak_planes`, :func:`_peak_window_near`): where weaker
    astigmatism leaves one peak, it lies between the foci too.
    """
    order, min_planes = options.amplitude_order, options.amplitude_order + 3
    window = _focus_window(z_nm, amplitude, options.focus_fraction, min_planes)
    model = PolyModel.from_estimate(z_nm, amplitude, order=order, mask=window)
    z_f, interior = peak(model)
    step = np.median(np.diff(z_nm, axis=1))
    half = np.sum(window, axis=1, keepdims=True) * step / 2
    centred = (np.abs(z_nm - z_f[:, None]) <= half) & np.isfinite(amplitude) & interior[:, None]
    centred |= window & ~interior[:, None]
    model = PolyModel.from_estimate(z_nm, amplitude, order=order, mask=centred)
    z_f, interior = peak(model)
    depth = _dip_depth(amplitude, window)
    twin = depth.max(axis=1) > DIP_FRACTION
    if not twin.any():
        return model, z_f, interior
    rows = np.flatnonzero(twin)
    sides = [_peak_window_near(z_nm[rows], amplitude[rows], target, options.focus_fraction,
                               min_planes)
             for target in _peak_planes(z_nm[rows], amplitude[rows], window[rows],
                                        depth[rows])]  # fmt: skip
    both = sides[0].any(axis=1) & sides[1].any(axis=1)  # else no focus of its own: not in focus
    z_f, interior = z_f.copy(), interior.copy()
    z_f[rows[~both]], interior[rows[~both]] = np.nan, False
    rows = rows[both]
    foci = [peak(PolyModel.from_estimate(z_nm[rows], amplitude[rows], order=order, mask=m[both]))
            for m in sides]  # fmt: skip
    z_f[rows] = (foci[0][0] + foci[1][0]) / 2
    interior[rows] = foci[0][1] & foci[1][1]
    return model, z_f, interior


def _peak_planes(
    z: np.ndarray, amp: np.ndarray, window: np.ndarray, depth: np.ndarray
) -> list[np.ndarray]:
    """z (nm, (n,) each) of the highest A (n, n_z) inside ``window`` on either side of its
    deepest dip (``depth``, :func:`_dip_depth`): the two line foci."""
    dip = np.argmax(depth, axis=1)
    idx = np.arange(amp.shape[1])
    filled = np.where(window & np.isfinite(amp), amp, -np.inf)
    left = np.argmax(np.where(idx < dip[:, None], filled, -np.inf), axis=1)
    right = np.argmax(np.where(idx > dip[:, None], filled, -np.inf), axis=1)
    rows = np.arange(len(amp))
    return [z[rows, left], z[rows, right]]


def _dip_depth(amp: np.ndarray, window: np.ndarray) -> np.ndarray:
    """(n, n_z) how far each trace's three-plane running mean of A (n, n_z) lies below the
    lower of its highest values on either side, within ``window`` (relative; −inf outside)."""
    inside = window & np.isfinite(amp)
    value = np.pad(np.where(inside, amp, 0.0), ((0, 0), (1, 1)))
    count = np.pad(inside.astype(float), ((0, 0), (1, 1)))
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = (value[:, :-2] + value[:, 1:-1] + value[:, 2:]) / (
            count[:, :-2] + count[:, 1:-1] + count[:, 2:]
        )
        smooth = np.where(inside, smooth, -np.inf)
        left = np.fmax.accumulate(smooth, axis=1)
        right = np.fmax.accumulate(smooth[:, ::-1], axis=1)[:, ::-1]
        lower = np.minimum(left, right)
        return np.where(inside, (lower - smooth) / lower, -np.inf)


def _peak_window_near(
    z: np.ndarray, amp: np.ndarray, target: np.ndarray, fraction: float, min_planes: int
) -> np.ndarray:
    """(n, n_z) mask of the planes about the local maximum of each trace's A (n, n_z) nearest
    its ``target`` (nm, (n,); ``z`` (n, n_z) nm): from that maximum down each side while A's
    three-plane running mean falls and A stays at least ``fraction`` of the maximum. A row is
    empty where that holds fewer than ``min_planes`` planes (no peak of its own there)."""
    n, n_z = amp.shape
    filled = np.where(np.isfinite(amp), amp, -np.inf)
    padded = np.pad(filled, ((0, 0), (1, 1)), mode="edge")
    smooth = (padded[:, :-2] + padded[:, 1:-1] + padded[:, 2:]) / 3
    out = np.zeros((n, n_z), dtype=bool)
    for row in range(n):
        i = int(np.argmin(np.abs(z[row] - target[row])))
        while True:  # climb to the local maximum of the running mean
            up = [j for j in (i - 1, i + 1) if 0 <= j < n_z and smooth[row, j] > smooth[row, i]]
            if not up:
                break
            i = max(up, key=lambda j: smooth[row, j])
        floor = fraction * filled[row, i]
        lo = hi = i
        while lo > 0 and smooth[row, lo - 1] <= smooth[row, lo] and filled[row, lo - 1] >= floor:
            lo -= 1
        while (hi < n_z - 1 and smooth[row, hi + 1] <= smooth[row, hi]
               and filled[row, hi + 1] >= floor):  # fmt: skip
            hi += 1
        if hi - lo + 1 >= min_planes:
            out[row, lo : hi + 1] = np.isfinite(amp[row, lo : hi + 1])
    return out


def fit_local(
    traces: Traces,
    shapes: tuple[str, ...],
    *,
    theta: float | None = None,
    options: LocalOptions = LocalOptions(),
) -> LocalModels:
    """Fit every local model of every particle of ``traces`` (piezo z axis).

    Parameters
    ----------
    traces : Traces
        Per-plane fit results.
    shapes : tuple of str
        Shape parameters to model (see :mod:`latentz.calibration.shape`).
    theta : float, optional
        Astigmatism angle (rad), needed for "auto" and "auto_A".
    options : LocalOptions
        Orders and windows.
    """
    n = len(traces)
    z = np.broadcast_to(traces.z_nm, (n, traces.z_nm.size)).copy()
    amp = traces["amplitude"]
    amplitude, z_f, interior = best_focus(z, amp, options)
    step = np.min(np.diff(traces.z_nm))
    in_focus = interior & (z_f > traces.z_nm[0] + step) & (z_f < traces.z_nm[-1] - step)

    run = measured_run(traces, z, z_f)
    lateral = {}
    for axis in ("x", "y"):
        model = PolyModel.from_estimate(z, traces[axis], order=options.lateral_order, mask=run)
        delta = model.shifted(model(z_f[:, None])[:, 0])
        residuals = np.where(run, delta.residuals(z, traces[axis] - model(z_f[:, None])), np.nan)
        sigma = sliding_rms(
            z, residuals, window_nm=options.sigma_window_nm, n_params=options.lateral_order + 1
        )
        lateral[axis] = (delta, sigma)

    wx, wy, rho = traces["wx"], traces["wy"], traces["rho"]
    models = {}
    for shape in shapes:
        ref = np.full(n, np.nan)
        if uses_amplitude(shape):
            ref = reference_amplitude(shape, wx, wy, rho, amp, theta=theta)
        values = shape_value(shape, wx, wy, rho, amp, theta=theta, amplitude_ref=ref[:, None])
        models[shape] = _shape_model(values, z, z_f, ref, options, run)
    return LocalModels(
        z_nm=z,
        z_f=z_f,
        in_focus=in_focus,
        amplitude=amplitude,
        dx=lateral["x"][0],
        dy=lateral["y"][0],
        sigma_dx=lateral["x"][1],
        sigma_dy=lateral["y"][1],
        shapes=models,
        theta=theta,
    )

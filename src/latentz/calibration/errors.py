"""The uncertainty model of :meth:`Calibration.apply`: what ``x_err_nm``, ``y_err_nm`` and
``z_err_nm`` are made of.

Independent parts, added in quadrature (three in z, four laterally):

1. **the fit's precision**: with the joint readout, the curvature of its distance to the
   calibration curves (:mod:`latentz.calibration.readout`); with the one shape value, the
   errors of the spot's fitted wx, wy, ρ, A propagated to it, then through the inverse
   function z(s) (:func:`spread_through`: the slope dz/ds times σ_s where σ_s is small against
   the curve's bend, the curve's spread within the particle's monotonic range where σ_s spans
   its steep ends); laterally, the fit's own x, y error, plus the z error (this part and the
   local model's) carried through Δx'(z), Δy'(z) alike, within where a spot in range lies;
2. **the local model's σ**: the uncertainty of the calibration particle's polynomial z(s) and
   Δx'(z), Δy'(z), from the residuals of its fit (σ at that z, divided by the square root of the
   number of planes per parameter); laterally also its lack of fit, the part of the residual σ
   that the traces' own fit errors do not explain (a fitted Gaussian wanders about any smooth
   curve near focus, and so does every emitter's, by another pattern);
3. **the field model's error**: how wrong the model of the field is between calibration
   particles, measured by cross-validation (:mod:`latentz.calibration.crossval`): in bins of z,
   the held-out squared errors of the chosen field model as a line ``a² + b² d²`` in the squared
   distance d to the nearest particle, evaluated at the spot's own distance and scaled to cover
   68 % of the held-out errors, which are heavy-tailed (laterally no nearer than the distances
   held out, less the held-out particle's own z noise carried through its Δx'(z), Δy'(z),
   which part 1 carries for a spot); in z, ``a²`` holds the particles'
   own heights, which a held-out error holds twice and a spot near one particle once
   (:func:`field_sigma`). In z it is no smaller than the same line measured on held-out
   particles seen as emitters of the spot's brightness and localized by their 1st-4th
   nearest other particles (:func:`~latentz.calibration.dim_crossval.pair_table`), which
   reaches twice the particles' spacing: a spot beyond the outer particles or in a gap is
   farther than any held-out one. That line is ``nearest``'s error; for another field model
   it counts only beyond the distances that model's cross-validation held out;
4. laterally, **the particle's own reference**: Δx', Δy' are measured from its centre at z_f,
   which under coma lies off its place by about as much as that centre travels within the
   depth of focus; neither part 2 nor the cross-validation of part 3 sees it
   (:func:`reference_sigma`).

Part 1 is checked against the calibration's own images (:func:`measured_noise`): where they
scatter about their z(s) curve less than their fit errors say, the camera's noise model
overstates the noise (a gain too low, or frames averaged before saving) and the fit's part is
scaled down to the measured scatter about each z (:func:`noise_by_z`).

Part 3 is what the paper's error estimate lacks: its fit residuals at the particles shrink as terms
are added, while the error between particles grows.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from latentz.calibration.polymodel import PolyModel

__all__ = [
    "field_sigma", "field_line", "FieldLine", "combine", "covering_width", "fit_covariance",
    "fit_sigma_s", "measured_noise", "noise_by_z", "reference_sigma", "spread_through",
]  # fmt: skip

#: Residual degrees of freedom in each window of :func:`noise_by_z` at least: its scale is known
#: there to 1/√(2·12) = 20 %.
NOISE_WINDOW = 12
#: Held-out planes per z bin; sparser bins are merged with their neighbours.
MIN_PER_BIN = 30
#: Share of a normal error within 1σ: the field line is scaled so that the held-out errors are
#: covered as often (:func:`_covering_scale`).
ONE_SIGMA = 0.6827
#: Field models that smooth over the particles rather than pass through them (:func:`field_sigma`).
SMOOTHING = ("zernike",)
#: Share of its peak amplitude A(z) above which a particle is within its depth of focus
#: (:func:`reference_sigma`): 1/√2, where the image's area (∝ photons / A) is √2 times its
#: smallest.
DEPTH_FRACTION = 2**-0.5
#: Equally spaced nodes (in σ) and normal weights for :func:`spread_through`: each node is clipped
#: to the span, so the normal's mass beyond an end sits at that end.
_NODES = np.linspace(-5.0, 5.0, 41)
_WEIGHTS = np.exp(-0.5 * _NODES**2) / np.exp(-0.5 * _NODES**2).sum()


def field_sigma(table: pd.DataFrame, model: str, axis: str, z_nm: np.ndarray,
                distance_px: np.ndarray, *, bin_nm: float = 250.0,
                model_nm: np.ndarray | None = None,
                noise_nm: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Field-model error (nm, 1σ) of ``model`` on ``axis`` ("x", "y" or "z") at each z and
    distance from the nearest calibration particle.

    Every model errs more the farther a spot is from the particles (for a smooth field, in
    proportion to that distance d), and by about the same at any distance where the particles
    themselves scatter about the field (each particle's own size, height and shape: a 1 µm bead
    of ±24 nm diameter sits ±12 nm off the surface). So the squared error is taken as
    ``a² + b² d²``: the held-out errors of ``table`` (:func:`~latentz.calibration.crossval.
    crossval`) are binned in z (``bin_nm`` wide, merged until each holds :data:`MIN_PER_BIN`
    planes), and in each bin ``a²`` and ``b²`` are the least-squares line of the squared errors
    against the squared held-out distances (:func:`_floor_and_slope`; neither negative). In z,
    a model that passes through its particles (``nearest``, ``natural``, ``curves``) errs at a
    spot by its particles' own heights, which a held-out error holds twice (the held-out
    particle's own, in the "truth" it is compared with, and its neighbours'), so ``a²/2`` is
    added; for ``natural`` and ``curves``, which average several neighbours, that is an upper
    bound. Laterally a particle has no such offset of its own (Δx', Δy' are measured from its
    own focus, and a bead's size does not move its image sideways), so ``a²`` there is the
    field's structure below the particles' spacing, which a spot meets in full: the whole
    ``a²`` is added, as in z for a model that smooths over the particles (:data:`SMOOTHING`: a
    few Zernike terms over the whole field), which misses the field at the particles too. ``a²``
    and ``b²`` are interpolated linearly at ``z_nm`` (held constant beyond the end bins) and
    evaluated at ``distance_px``; laterally no nearer than the 10th percentile of the held-out
    distances. Below those the line is an extrapolation, and laterally, where the floor is the
    field's fine structure, a spot near a particle errs as much as one at the particles'
    spacing (validation microscope: 5.9–7.6 nm RMS at 1–2.5 µm for emitters 7–15 px from a
    particle, against 2.8–3.6 nm from the line). In z the floor holds the particles' heights
    and the line is kept down to d = 0: on latentz's simulator, z errors near particles do
    shrink (held at the spacing, 1σ covers 87 % there).
    Planes the model did not predict do not count. NaN z gives NaN.

    ``model_nm`` (one per row of ``table``) is the 1σ of the held-out particle's own local model
    at that plane. A held-out error is the field model's error plus two local-model errors that
    do not grow with distance: the held-out particle's (its polynomial is the "truth" it is
    compared with) and its neighbours' (the field model is built from their polynomials; at a
    spot, :meth:`~latentz.calibration.Calibration.apply` adds the nearest particle's as the
    local model's σ). Both are of the size of ``model_nm`` (polynomials fitted alike through as
    many planes), so ``2 model_nm²`` is subtracted from each squared error before the RMS (the
    difference clipped at zero): otherwise they are counted twice and grow with distance.
    ``noise_nm`` (one per row) is any further part of each held-out error that a spot's σ holds
    elsewhere, subtracted once (laterally: the held-out particle's own z noise carried through
    its Δx'(z), Δy'(z), which a spot's own σ_z stands for).

    The line of each bin is then scaled so that, with those parts, it covers :data:`ONE_SIGMA`
    of the bin's held-out errors (:func:`_covering_scale`): they are heavy-tailed (a few
    particles and planes hold most of the mean square), and a normal of their mean square spans
    most of the others many times over. In z this holds on the validation family's draws and
    the independent validation microscope, whose test emitters' errors have such tails too.
    """
    line = field_line(table, model, axis, bin_nm=bin_nm, model_nm=model_nm, noise_nm=noise_nm)
    return line.sigma(z_nm, distance_px)


class FieldLine(NamedTuple):
    """The squared error line ``a² + b² d²`` of :func:`field_sigma` in each z bin: bin centres
    (nm), ``a²`` and ``b²`` (nm², nm² / px²) at them, the share of ``a²`` a spot meets (1 or
    1/2) and the squared distance (px²) below which the line is not extrapolated. Fixed for a
    calibration: made once (:func:`field_line`), read for any spots (:meth:`sigma`)."""

    centres: np.ndarray
    floor2: np.ndarray
    slope2: np.ndarray
    floor_share: float
    least_d2: float

    def sigma(self, z_nm: np.ndarray, distance_px: np.ndarray) -> np.ndarray:
        """The field-model error (nm, 1σ) at each z (nm) and distance (px); NaN z gives NaN."""
        z = np.asarray(z_nm, dtype=np.float64)
        if self.centres.size == 0:
            return np.full(z.shape, np.nan)
        floor2 = np.interp(z, self.centres, self.floor2) * self.floor_share
        slope2 = np.interp(z, self.centres, self.slope2)
        d2 = np.maximum(np.asarray(distance_px, dtype=np.float64) ** 2, self.least_d2)
        return np.where(np.isfinite(z), np.sqrt(floor2 + slope2 * d2), np.nan)


def field_line(table: pd.DataFrame, model: str, axis: str, *, bin_nm: float = 250.0,
               model_nm: np.ndarray | None = None,
               noise_nm: np.ndarray | None = None) -> FieldLine:  # fmt: skip
    """The :class:`FieldLine` of :func:`field_sigma` (same arguments, less the spots')."""
    use = ((table["model"] == model) & table["in_range"]).to_numpy()
    rows = table[use]
    if len(rows) == 0:
        return FieldLine(np.empty(0), np.empty(0), np.empty(0), 1.0, 0.0)
    order = np.argsort(rows["z_nm"].to_numpy())
    zz = rows["z_nm"].to_numpy()[order]
    err2 = rows[f"err_{axis}_nm"].to_numpy()[order] ** 2
    known2 = np.zeros(zz.size)
    if model_nm is not None:
        known = np.asarray(model_nm, dtype=np.float64)[use][order]
        known2 += 2 * np.where(np.isfinite(known), known, 0.0) ** 2
    if noise_nm is not None:
        noise = np.asarray(noise_nm, dtype=np.float64)[use][order]
        known2 += np.where(np.isfinite(noise), noise, 0.0) ** 2
    dist2 = rows["distance_px"].to_numpy()[order] ** 2
    edges = np.arange(zz[0], zz[-1] + bin_nm, bin_nm)
    ends = np.cumsum(np.bincount(np.searchsorted(edges, zz, side="right") - 1))
    centres, bins, first = [], [], 0
    for end in ends:  # merge consecutive bins until each holds enough planes
        if end - first >= MIN_PER_BIN or (end == zz.size and not bins):
            centres.append(np.mean(zz[first:end]))
            bins.append(np.arange(first, end))
            first = end
    if first < zz.size:  # a short last run joins the last bin
        bins[-1] = np.flatnonzero(zz >= centres[-1])
    values = [_bin_line(err2[b], known2[b], dist2[b]) for b in bins]
    floor2, slope2 = np.asarray(values).T
    # in z, the spot's neighbours' heights, not the held-out particle's too (see field_sigma)
    share = 0.5 if model not in SMOOTHING and axis == "z" else 1.0
    # laterally no extrapolation below the distances held out (see field_sigma)
    least_d2 = float(np.quantile(dist2, 0.1)) if axis != "z" else 0.0
    return FieldLine(np.asarray(centres), floor2, slope2, share, least_d2)


def _bin_line(err2: np.ndarray, known2: np.ndarray, dist2: np.ndarray) -> tuple[float, float]:
    """``(a², b²)`` of one z bin's held-out squared errors ``err2`` less the parts ``known2``
    that a spot's σ holds elsewhere, against the squared distances ``dist2``
    (:func:`_floor_and_slope`), scaled by the k² at which ``k²(a² + b²d²) + known2`` covers
    :data:`ONE_SIGMA` of the squared errors, as a spot's σ should (:func:`_covering_scale`)."""
    floor2, slope2 = _floor_and_slope(err2 - known2, dist2)
    k2 = _covering_scale(err2, known2, floor2 + slope2 * dist2)
    return k2 * floor2, k2 * slope2


def _covering_scale(err2: np.ndarray, known2: np.ndarray, line2: np.ndarray) -> float:
    """The least k² ≥ 0 with ``err2 ≤ k² line2 + known2`` on :data:`ONE_SIGMA` of the rows.

    The line is a mean square: where a few held-out errors are far larger than the rest (a
    particle at a defect, the planes where a curve flattens), a normal of that variance spans
    most of the others many times over, and where the errors are nearer alike than a normal's,
    too few. Rows where the line is zero (at a particle, without a floor) do not count."""
    reach = line2 > 0
    if not reach.any():
        return 1.0
    needed = np.maximum(err2[reach] - known2[reach], 0.0) / line2[reach]
    return float(np.quantile(needed, ONE_SIGMA))


def _floor_and_slope(err2: np.ndarray, dist2: np.ndarray) -> tuple[float, float]:
    """``(a², b²)`` of the least-squares line ``err² = a² + b² d²`` (``dist2`` = d²), neither
    negative: with a negative slope the mean square alone, with a negative floor the line
    through the origin that keeps the mean square, ``b² = mean(err²) / mean(d²)``."""
    mean_e, mean_d = max(float(np.mean(err2)), 0.0), float(np.mean(dist2))
    if mean_d <= 0:  # held out at the particles' own places: no growth to measure
        return mean_e, 0.0
    spread = float(np.mean((dist2 - mean_d) ** 2))
    slope = float(np.mean((dist2 - mean_d) * (err2 - np.mean(err2)))) / spread if spread else 0.0
    if slope <= 0:
        return mean_e, 0.0
    floor = mean_e - slope * mean_d
    if floor < 0:
        return 0.0, mean_e / mean_d
    return floor, slope


def reference_sigma(positions: np.ndarray, delta: PolyModel, z_f: np.ndarray,
                    span: np.ndarray, half_depth_nm: float, *,
                    points: int = 21) -> float:  # fmt: skip
    """1σ (``delta``'s units) of the particles' lateral reference: how far their fitted centres
    travel off the field's plane within the depth of focus.

    Δ(z) is measured from each particle's centre at its best focus ``z_f`` (nm, (n,)), taken to
    be its place. With coma the fitted centre moves through focus, and where along that travel
    the place lies the images do not say; the same coma moves the reference at z_f, across the
    field as it moves the travel. Only the part of the references that is not a plane across
    the field is an error (a plane is a shift, tilt or scale of the whole field). So at each of
    ``points`` offsets t from −``half_depth_nm`` to +``half_depth_nm`` the least-squares plane
    in ``positions`` ((n, 2), px) of the particles' Δ(z_f + t) is taken off, and the σ is the
    RMS of what remains over the particles and the t within each one's ``span`` ((n, 2), nm;
    Δ is not extrapolated): the reference's error if the place lies anywhere along the travel
    within the depth, evenly. Zero with fewer than four particles at every t (no plane to take
    off with any left over)."""
    n = len(positions)
    t = np.linspace(-half_depth_nm, half_depth_nm, points)
    z = np.asarray(z_f, dtype=np.float64)[:, None] + t[None]
    inside = (z >= span[:, :1]) & (z <= span[:, 1:])
    values = np.where(inside, delta(np.where(inside, z, 0.0)), np.nan)
    design = np.column_stack([np.ones(n), positions])
    squares = []
    for k in range(points):
        use = np.isfinite(values[:, k])
        if use.sum() >= 4:
            coef = np.linalg.lstsq(design[use], values[use, k], rcond=None)[0]
            squares.append((values[use, k] - design[use] @ coef) ** 2)
    return float(np.sqrt(np.mean(np.concatenate(squares)))) if squares else 0.0


def spread_through(
    model: PolyModel,
    at: np.ndarray,
    sigma: np.ndarray,
    span: np.ndarray,
    limits: np.ndarray | None = None,
    *,
    covering: bool = False,
) -> np.ndarray:
    """1σ (the model's units, (n,)) of ``model(a') − model(a)`` for a' normal about each row's
    ``at`` with σ ``sigma`` (the model's argument's units), each a' held within its row's
    ``span`` ((n, 2); a spot in range lies there) and, with ``limits`` ((n, 2)), each value
    held within them (where a spot in range is placed). |model'(a)|·σ where σ is small
    against the curve's bend; where σ spans the curve (weak astigmatism: σ_z of microns, or
    σ_s across the whole inverse z(s)), the curve's spread over the span, not a slope times a
    σ many times wider, nor the slope of an order-16 polynomial's wiggle (or the zero of its
    derivative at a turn of one). The root mean square of the differences, or with
    ``covering`` the least |difference| that holds :data:`ONE_SIGMA` of the normal's weight
    (the same |model'(a)|·σ on a straight curve; on a curve that steepens towards the span's
    ends, not ruled by the few a' there). NaN where σ is."""
    sigma = np.asarray(sigma, dtype=np.float64)
    offsets = sigma[:, None] * _NODES[None]
    offsets[:, _NODES == 0] = 0.0  # the centre, also where σ is infinite
    a = np.asarray(at, dtype=np.float64)[:, None]
    values = model(np.clip(a + offsets, span[:, :1], span[:, 1:]))
    if limits is not None:
        values = np.clip(values, limits[:, :1], limits[:, 1:])
    spread = np.abs(values - values[:, _NODES == 0])
    width = covering_width(spread, _WEIGHTS) if covering else np.sqrt(spread**2 @ _WEIGHTS)
    return np.where(np.isnan(sigma), np.nan, width)


def covering_width(spread: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n,) per row of |differences| ``spread`` (n, nodes) of ``weights`` ((nodes,) or (n,
    nodes), each row's summing to 1), the one that holds :data:`ONE_SIGMA` of the weight: each
    node's weight spread about its value (the cumulative weight at a value is that of the nodes
    below it and half its own), linear between the values."""
    order = np.argsort(spread, axis=1)
    values = np.take_along_axis(spread, order, axis=1)
    weights = np.take_along_axis(np.broadcast_to(weights, spread.shape), order, axis=1)
    held = np.cumsum(weights, axis=1) - weights / 2
    above = np.clip(np.argmax(held >= ONE_SIGMA, axis=1), 1, spread.shape[1] - 1)
    rows = np.arange(len(spread))
    lo, hi = held[rows, above - 1], held[rows, above]
    share = np.clip((ONE_SIGMA - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
    return values[rows, above - 1] + share * (values[rows, above] - values[rows, above - 1])


def combine(*parts: np.ndarray) -> np.ndarray:
    """Root of the sum of squares of independent 1σ errors (NaN parts count as zero)."""
    total = np.zeros(np.broadcast_shapes(*(np.shape(p) for p in parts)))
    for p in parts:
        total = total + np.where(np.isfinite(p), np.square(p), 0.0)
    return np.sqrt(total)


def fit_covariance(
    params: np.ndarray,
    errors: np.ndarray,
    correlations: np.ndarray | None,
    *,
    roi_size: int,
    readnoise: float,
) -> np.ndarray:
    """Covariance (n, 4, 4) of each spot's fitted (amplitude, wx, wy, ρ).

    ``params`` (n, 7) are the fitted x, y, amplitude, background, wx, wy, ρ (photoelectrons,
    px); ``errors`` (n, 4) the standard deviations of amplitude, wx, wy, ρ (the fit's ``*_err``
    columns: the sandwich covariance of :mod:`latentz.fit.robust`); ``correlations`` (n, 6) their
    correlations (:data:`latentz.fit.api.CORRELATED`, the fit's ``*_corr`` columns). wx and wy
    are strongly correlated (about +0.6), and so are ρ and the widths out of focus. Where the
    correlations are not given (a table without ``*_corr`` columns) they are those of the
    Cramér–Rao covariance of the Gaussian at the fitted parameters centred in a ROI of
    ``roi_size`` (the information hardly depends on the position); zero where that is not
    usable either.
    """
    from latentz.fit._model import PARAMS, covariance
    from latentz.fit.api import CORRELATED, correlations_of

    params = np.array(params, dtype=np.float64)
    n = len(params)
    which = [PARAMS.index(k) for k in ("amplitude", "wx", "wy", "rho")]
    sd = np.asarray(errors, dtype=np.float64).reshape(n, 4)
    corr = np.full((n, len(CORRELATED)), np.nan)
    if correlations is not None:
        corr = np.array(correlations, dtype=np.float64).reshape(n, len(CORRELATED))
    missing = ~np.all(np.isfinite(corr), axis=1) & np.all(np.isfinite(params), axis=1)
    if missing.any():
        p = params[missing].copy()
        p[:, 0] = p[:, 1] = (roi_size - 1) / 2
        corr[missing] = correlations_of(covariance(p, shape=roi_size, readnoise=readnoise))
    corr = np.where(np.isfinite(corr), corr, 0.0)
    r = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for c, (a, b) in enumerate(CORRELATED):
        ka, kb = which.index(PARAMS.index(a)), which.index(PARAMS.index(b))
        r[:, ka, kb] = r[:, kb, ka] = corr[:, c]
    return sd[:, :, None] * r * sd[:, None, :]


def fit_sigma_s(
    shape: str,
    params: np.ndarray,
    errors: np.ndarray,
    correlations: np.ndarray | None,
    *,
    roi_size: int,
    readnoise: float,
    theta: float | None,
    amplitude_ref: np.ndarray,
) -> np.ndarray:
    """The fit's 1σ error of each spot's shape value s, with the parameters' covariances.

    The gradient of s in (amplitude, wx, wy, ρ) is carried through their covariance
    (:func:`fit_covariance`, of the same arguments): the diagonal alone misses by up to a
    factor of 1.5.
    """
    from latentz.calibration.shape import shape_value
    from latentz.fit._model import PARAMS

    params = np.array(params, dtype=np.float64)
    n = len(params)
    cov = fit_covariance(params, errors, correlations, roi_size=roi_size, readnoise=readnoise)
    sd = np.sqrt(np.diagonal(cov, 0, 1, 2))
    ref = np.broadcast_to(np.asarray(amplitude_ref, dtype=np.float64), (n,))
    grad = np.zeros((n, 4))
    for k, name in enumerate(("amplitude", "wx", "wy", "rho")):
        i = PARAMS.index(name)
        step = np.maximum(np.abs(sd[:, k]), 1e-9) * 1e-3
        hi, lo = params.copy(), params.copy()
        hi[:, i] += step
        lo[:, i] -= step
        value = [shape_value(shape, q[:, 4], q[:, 5], q[:, 6], q[:, 2], theta=theta,
                             amplitude_ref=ref) for q in (hi, lo)]  # fmt: skip
        grad[:, k] = (value[0] - value[1]) / (2 * step)
    variance = np.einsum("ni,nij,nj->n", grad, cov, grad)
    return np.sqrt(np.maximum(variance, 0.0))


def measured_noise(
    residual_nm: np.ndarray,
    predicted_nm: np.ndarray,
    *,
    n_params: int,
    n_fitted: np.ndarray | None = None,
) -> float:
    """How much less the calibration's own images scatter in z than their fit errors say.

    ``residual_nm`` (n, n_z): each calibration image's z minus its particle's z(s) curve;
    ``predicted_nm`` (n, n_z): the fit's part of ``z_err_nm`` for that image, as
    :meth:`~latentz.calibration.Calibration.apply` computes it for a spot (NaN for images not to
    count); ``n_params``: the parameters of each curve; ``n_fitted`` (n,): the images each curve
    was fitted to (by default those that count). Returns r, the root mean square of each
    image's residual over its predicted error (each particle's squares corrected by
    ``f / (f − n_params)`` for its ``f`` fitted images: a least-squares curve's residuals are
    that much smaller than the images' scatter, on average over the images it was fitted to,
    however few of them count), where r is below 1 by more than twice its sampling error
    (``1/sqrt(2 ν)``, ν the curves' residual degrees of freedom, the sum of their
    ``f − n_params``), else 1. A curve through no more images than it has parameters follows
    them exactly and does not count. Each image counts once: a
    ratio of RMS values would be ruled by the few planes where the curve is flat and the
    predicted error huge. The curve's lack of fit, stage jitter and flicker only add scatter, so
    r < 1 means the pixels are less noisy than the camera model says (a gain too low, frames
    averaged): every fit error, at any brightness, is r times too large.
    """
    use = np.isfinite(residual_nm) & np.isfinite(predicted_nm) & (predicted_nm > 0)
    count = use.sum(axis=1)
    fitted = count if n_fitted is None else np.asarray(n_fitted)
    free = np.maximum(fitted - n_params, 0)
    counts = free > 0
    m = int(count[counts].sum())
    if m == 0:
        return 1.0
    nu = float(np.sum(free))
    normalised2 = np.where(use, residual_nm / np.where(use, predicted_nm, 1.0), 0.0) ** 2
    inflate = fitted[counts] / free[counts]
    ratio = float(np.sqrt(np.sum(inflate * np.sum(normalised2[counts], axis=1)) / m))
    return ratio if ratio < 1 - 2 / np.sqrt(2 * nu) else 1.0


def noise_by_z(
    z_nm: np.ndarray,
    scatter2: np.ndarray,
    free: np.ndarray,
    *,
    window: int = NOISE_WINDOW,
    spans: int = 16,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`measured_noise` as a function of z: how much less the calibration images scatter
    than their fit errors say, about each z.

    ``z_nm`` (m,): each image's z; ``scatter2`` (m,): its squared residual about its curve over
    its predicted error squared; ``free`` (m,): ``1 − h``, h its leverage in the curve's fit
    (:meth:`~latentz.calibration.polymodel.PolyModel.leverage`), the share of the image's noise
    its residual keeps. About a z, r² is the window's summed ``scatter2`` over its summed
    ``free``. Images sorted by z are taken in running windows of as many consecutive images as
    hold ``window`` residual degrees of freedom on average (each r then known to about
    ``1/sqrt(2 · window)``), or a ``spans``-th of the images where they are many. Returns each
    window's mean z (nm, ascending, distinct) and its r, at most 1; empty where the images
    hold fewer than two windows.
    """
    use = np.isfinite(z_nm) & np.isfinite(scatter2) & (np.asarray(free) > 0)
    z, q, f = (np.asarray(v)[use] for v in (z_nm, scatter2, free))
    if z.size == 0:
        return np.empty(0), np.empty(0)
    size = max(int(np.ceil(window / np.mean(f))), z.size // spans)
    if z.size < 2 * size:
        return np.empty(0), np.empty(0)
    order = np.argsort(z, kind="stable")
    zs, qs, fs = (np.convolve(v[order], np.ones(size), mode="valid") for v in (z, q, f))
    centre, index = np.unique(zs / size, return_inverse=True)
    mean2 = np.bincount(index, weights=qs / fs) / np.bincount(index)
    return centre, np.minimum(np.sqrt(mean2), 1.0)

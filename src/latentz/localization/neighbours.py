"""Crowded ROIs: fit each spot again with its detected neighbours' light taken out.

A ROI (15 px with a default calibration) often holds part of another emitter's image; one
Gaussian of eq. 1 fitted to it takes up that light, which biases its position and widths, and
so z. :func:`refit_without_neighbours` subtracts, from each ROI, eq. 1 of every other fit of the
same frame whose centre lies within :data:`REACH_PX` of the ROI (its amplitude, widths and ρ;
not its background) and fits the ROI again from its first fit, :data:`PASSES` times, each pass
with the neighbours' fits of the pass before. The refit's Pearson χ² counts the subtracted
light's shot noise in each pixel's variance (:mod:`.crowding` reads it). Fits within
`DUPLICATE_PX` of each other are one emitter (:func:`latentz.localization.pairs.copies`): a
spot's own copies are not subtracted from it, and of a neighbour's copies only the first is.
Only converged fits are subtracted, and a refit replaces the first fit only where it converged.
Emitters that were not detected stay in the ROI: :mod:`.crowding` puts their bias in the errors.
"""

from __future__ import annotations

import numpy as np

from latentz.fit._model import model_and_jacobian
from latentz.fit.api import FitResult, fit_arrays, replace_rows
from latentz.localization.pairs import box_pairs, copies

__all__ = ["refit_without_neighbours", "neighbour_light", "REACH_PX", "PASSES"]

#: A neighbour whose centre lies this far (pixels, in x and y) beyond the ROI's edge or closer
#: is subtracted: three widths of an in-focus spot, where its light falls below 2 % of its peak.
REACH_PX = 4.0
#: Fits of each crowded ROI: the second starts from neighbours that were themselves refitted.
PASSES = 2


def neighbour_light(
    params: np.ndarray, frame: np.ndarray, corner: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """Expected photoelectrons (n, h, w) that the other fits put into each ROI.

    ``params`` (n, 7) are fits in full-frame pixels (`latentz.fit.PARAMS`), ``frame`` (n,) their
    frames, ``corner`` (n, 2) each ROI's first column and row, ``shape`` the ROIs' (h, w).
    """
    n = len(params)
    rows, light = _light_into(params, frame, corner, shape)
    out = np.zeros((n, shape[0] * shape[1]))
    out[rows] = light
    return out.reshape(n, *shape)


def _light_into(
    params: np.ndarray, frame: np.ndarray, corner: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The ROIs that another fit's light reaches (indices, ascending) and that light (k, h * w,
    photoelectrons); arguments as `neighbour_light`. Most ROIs of a frame receive none, so
    only these are made."""
    h, w = shape
    usable = np.isfinite(params).all(axis=1)
    centre = corner + [(w - 1) / 2, (h - 1) / 2]
    into, src = box_pairs(centre, frame, params[:, :2], frame, max(h, w) / 2 + REACH_PX)
    near = usable[src] & (into != src)
    into, src = into[near], src[near]
    if into.size == 0:
        return into, np.zeros((0, h * w))
    # one fit per emitter, none of the ROI's own
    group = copies(params[:, 0], params[:, 1], frame)
    keep = (group[src] == src) & (group[src] != group[into])
    into, src = into[keep], src[keep]
    # summed in the order of the neighbours' positions: the same light whatever the rows' order
    order = np.lexsort((params[src, 1], params[src, 0], into))
    into, src = into[order], src[order]
    rows, first = np.unique(into, return_index=True)
    if rows.size == 0:
        return rows, np.zeros((0, h * w))
    local = params[src].copy()
    local[:, :2] -= corner[into]
    local[:, 3] = 0.0  # the background is the ROI's own
    model = model_and_jacobian(local, (h, w), jacobian=False)[0]
    # each ROI's neighbours added one after another, in order (np.add.reduceat sums three or
    # more in another order: other bits)
    count = np.diff(first, append=len(into))
    light = model[first]
    for k in range(1, count.max()):
        more = count > k
        light[more] += model[first[more] + k]
    return rows, light


def _pearson(
    params: np.ndarray, rois: np.ndarray, light: np.ndarray, readnoise: float
) -> np.ndarray:
    """Pearson χ² of fits ``params`` (n, 7, ROI px) to ``rois`` less the neighbours' ``light``
    (n, h, w), over the pixels inside the frame: the subtracted light's shot noise counts in
    each pixel's variance, ``mu + light + readnoise²``."""
    mu = model_and_jacobian(params, rois.shape[1:], jacobian=False)[0].reshape(rois.shape)
    light = light.reshape(rois.shape)
    with np.errstate(invalid="ignore"):
        terms = (rois - light - mu) ** 2 / np.maximum(mu + light + readnoise**2, 1e-12)
    return np.nansum(terms, axis=(1, 2))


def refit_without_neighbours(
    fit: FitResult,
    rois: np.ndarray,
    corner: np.ndarray,
    frame: np.ndarray,
    windows: np.ndarray | None,
    *,
    method: str,
    readnoise: float,
    device: str = "cpu",
) -> FitResult:
    """``fit`` (x, y in full-frame pixels) with every ROI that holds another fit's light fitted
    again with that light subtracted (see the module docstring); errors are the sandwich's, and
    ``chi2`` counts the subtracted light's shot noise in each pixel's variance.

    ``rois`` (n, h, w) are the photoelectrons the fits were made in (NaN outside the frame),
    ``corner`` (n, 2) their first column and row, ``frame`` (n,) their frames, ``windows`` the
    pixels inside the frame (:mod:`latentz.fit.windows`) or None.
    """
    shape = rois.shape[1:]
    for _ in range(PASSES):
        params = np.where(fit.converged[:, None], fit.params, np.nan)
        rows, light = _light_into(params, frame, corner, shape)
        lit = light.max(axis=1) > 0
        if not lit.any():
            return fit
        crowded = np.zeros(len(params), bool)
        crowded[rows[lit]] = True
        light = light[lit].reshape(-1, *shape)
        start = fit.params[crowded].copy()
        start[:, :2] -= corner[crowded]
        refit = fit_arrays(
            rois[crowded] - light, method=method, readnoise=readnoise, init=start,
            windows=None if windows is None else windows[crowded], device=device,
            errors="sandwich",
        )  # fmt: skip
        chi2 = _pearson(refit.params, rois[crowded], light, readnoise)
        refit = refit._replace(chi2=chi2)
        params = refit.params.copy()
        params[:, :2] += corner[crowded]
        better = np.zeros(len(crowded), bool)
        better[crowded] = refit.converged
        kept = refit._replace(params=params)
        fit = replace_rows(fit, FitResult(*(f[refit.converged] for f in kept)), better)
    return fit

"""Public fitting API: `fit_arrays` (arrays) and `fit_rois` (table), over the numba kernels."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numba
import numpy as np
import pandas as pd

from latentz._shared.engine import resolve_device
from latentz._shared.threads import SMALL_BATCH, one_thread_if
from latentz._shared.validate import check_array, check_choice, check_int, check_positive
from latentz.camera import Camera
from latentz.fit import _kernels
from latentz.fit._model import PARAMS, as_param_array, photons_of
from latentz.fit.robust import sandwich_batch
from latentz.fit.windows import MIN_SIDE, check_windows, window_groups

__all__ = ["FitResult", "fit_arrays", "fit_rois", "starts_at_peaks", "METHODS", "FIT_COLUMNS"]

METHODS = {"lsq": _kernels.LSQ, "wlsq": _kernels.WLSQ, "mle": _kernels.MLE}
ERROR_COLUMNS = tuple(f"{name}_err" for name in PARAMS)
#: Parameter pairs whose correlation the fit reports: those of the shape value (amplitude, wx,
#: wy, ρ), whose errors are strongly correlated (wx, wy about +0.6).
CORRELATED = (("amplitude", "wx"), ("amplitude", "wy"), ("amplitude", "rho"), ("wx", "wy"),
              ("wx", "rho"), ("wy", "rho"))  # fmt: skip
CORRELATION_COLUMNS = tuple(f"{a}_{b}_corr" for a, b in CORRELATED)
#: Columns of the table returned by `fit_rois`, in order.
FIT_COLUMNS = (
    *PARAMS,
    "photons",
    *ERROR_COLUMNS,
    "loglik",
    "chi2",
    "iterations",
    "converged",
    *CORRELATION_COLUMNS,
)
_RHO_MAX = 0.95
_W_MIN = 0.3


class FitResult(NamedTuple):
    """Arrays returned by `fit_arrays`, one row per ROI.

    Attributes
    ----------
    params : ndarray (n, 7)
        x, y (px, ROI coordinates), amplitude, background (photoelectrons), wx, wy (px), rho.
    errors : ndarray (n, 7)
        Standard deviations of ``params``: for "mle" and "wlsq" (whose fixed point is the
        Poisson maximum-likelihood fit) the sandwich covariance of a misspecified model
        (:mod:`latentz.fit.robust`), which holds the scatter of a real PSF's fit where the
        Cramér–Rao bound understates it by up to 1.6x; the Cramér–Rao bound where the sandwich
        is not usable (its observed information not positive definite), for "lsq" and with
        ``errors="crlb"`` (from the Fisher information of the last iterate whose derivatives
        were evaluated, at most one bound from the fit).
    loglik : ndarray (n,)
        Log-likelihood of the data under ``d + s^2 ~ Poisson(mu + s^2)`` at the fit.
    chi2 : ndarray (n,)
        Pearson chi-square, ``sum (d - mu)^2 / (mu + s^2)``.
    iterations : ndarray (n,) of int
        Levenberg–Marquardt iterations taken.
    converged : ndarray (n,) of bool
        False for a ROI with a non-finite pixel, a fit that stalled or hit ``max_iter``, a fit
        that ended on a parameter bound (other than the background's), a singular Fisher
        information, or a position bound (x_err or y_err) wider than the ROI.
    correlations : ndarray (n, 6)
        Correlations of the pairs `CORRELATED` in the sandwich covariance; NaN where ``errors``
        is the Cramér–Rao bound (its correlations follow from the parameters:
        :func:`latentz.fit._model.covariance`).
    """

    params: np.ndarray
    errors: np.ndarray
    loglik: np.ndarray
    chi2: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    correlations: np.ndarray


def parameter_bounds(shape: tuple[int, int], readnoise: float) -> tuple[np.ndarray, np.ndarray]:
    """Box of the internal parameters (x, y, A, B, log wx, log wy, atanh rho) for ROIs of ``shape``.

    Positions may leave the ROI by one pixel, widths lie in [0.3, max(h, w)] px, ``|rho| <= 0.95``
    and the background keeps ``mu + readnoise^2`` positive.
    """
    h, w = shape
    s2 = readnoise**2
    lower = np.array(
        [-1.0, -1.0, 0.0, -s2 + 1e-3, math.log(_W_MIN), math.log(_W_MIN), -math.atanh(_RHO_MAX)]
    )
    upper = np.array(
        [w, h, np.inf, np.inf, math.log(max(h, w)), math.log(max(h, w)), math.atanh(_RHO_MAX)]
    )
    return lower, upper


def starts_at_peaks(rois: Any, peaks: Any, windows: Any = None) -> np.ndarray:
    """Starting values (n, 7) for `fit_arrays`'s ``init``: the moment start
    (:func:`~latentz.fit.moment_start`) with each spot's peak at the pixel ``peaks`` (n, 2)
    gives, (row, col) in ROI pixels, such as where a detector found its maximum. The ROI's
    brightest box, where the plain moment start puts the peak, may be a brighter neighbour's,
    which then draws the fit to itself. With ``windows`` (as in `fit_arrays`), each start is
    taken from its window's pixels; x, y in the whole ROI's pixels. Computed by the numba
    kernels, in parallel."""
    data = np.ascontiguousarray(check_array("rois", rois, ndim=3, dtype_kind="uif"), np.float64)
    n, h, w = data.shape
    at = np.asarray(peaks)
    if at.shape != (n, 2) or not np.issubdtype(at.dtype, np.integer):
        raise ValueError(f"Expected `peaks` of ({n}, 2) integer pixels, got {at.shape} {at.dtype}.")
    checked = check_windows(windows, n, (h, w))
    if checked is None:
        checked = np.tile(np.array([0, h, 0, w], np.int64), (n, 1))
    if np.any(at < checked[:, [0, 2]]) or np.any(at >= checked[:, [1, 3]]):
        raise ValueError("Expected each of `peaks` inside its ROI's window.")
    out = np.empty((n, len(PARAMS)))
    rows, cols = (np.ascontiguousarray(a, np.int64) for a in at.T)
    _kernels.peak_starts(data, rows, cols, np.ascontiguousarray(checked), MIN_SIDE, out)
    return out


def fit_arrays(
    rois: Any,
    *,
    method: str = "mle",
    readnoise: float = 0.0,
    init: Any = None,
    max_iter: int = 50,
    tol: float = 1e-2,
    device: str = "auto",
    errors: str = "crlb",
    windows: Any = None,
) -> FitResult:
    """Fit eq. 1 to each ROI of a stack in photoelectrons; the array core of `fit_rois`.

    Parameters
    ----------
    rois : array_like (n, h, w)
        Photoelectrons per pixel. h and w must be at least 3.
    method : {"mle", "wlsq", "lsq"}
        Estimator; see `fit_rois`.
    readnoise : float
        Read-noise standard deviation in photoelectrons (>= 0).
    init : array_like (n, 7) or DataFrame, optional
        Starting values in natural parameters (columns of `PARAMS`); a row with a non-finite
        value falls back to the moment start. Default: moment start for every ROI.
    max_iter : int
        Maximum Levenberg–Marquardt iterations per ROI.
    tol : float
        The fit stops within about ``tol`` Cramér–Rao bounds of the optimum (for "lsq", of its
        own errors at the mean pixel variance): when the next step is at most ``tol`` bounds
        long, when the step after an unevaluated last one would be (:mod:`latentz.fit._kernels`),
        or when an accepted step lowered the objective by at most ``tol^2``. Below about 1e-6,
        float64 may not resolve the objective's changes on noisy ROIs.
    device : {"auto", "cpu", "cuda"}
        Where to fit (:func:`latentz._shared.engine.resolve_device`): the CPU cores, or one GPU
        thread
        per ROI in numba's CUDA target (extra ``latentz[gpu]``); the results agree.
    errors : {"crlb", "sandwich"}
        ``"crlb"`` (default): the Cramér–Rao bound, exact when the spots are the Gaussian of
        eq. 1 (correlations NaN). ``"sandwich"``: the covariance of a misspecified fit
        (`FitResult`), which holds the scatter when real PSFs are fitted with the Gaussian (as
        `latentz.localize` does); on the CPU after the fit, about 1.5x the fit's own time.
    windows : array_like (n, 4) of int, optional
        Per ROI, the pixels the fit sees: ``(row_start, row_stop, col_start, col_stop)``
        (:mod:`latentz.fit.windows`); the others, such as those outside the frame, are left out
        of the likelihood, and x, y stay in the whole ROI's pixels. A window narrower than 3 px
        gives a failed fit. ROIs whose window is not whole are fitted on the CPU. Default: every
        ROI whole.

    Returns
    -------
    FitResult
    """
    data = check_array("rois", rois, ndim=3, dtype_kind="uif")
    n, h, w = data.shape
    if h < 3 or w < 3:
        raise ValueError(f"Expected ROIs of at least 3 x 3 pixels, got shape {data.shape}.")
    code = METHODS[check_choice("method", method, METHODS)]
    s2 = check_positive("readnoise", readnoise, allow_zero=True) ** 2
    max_iter = check_int("max_iter", max_iter, minimum=1)
    tol = check_positive("tol", tol)
    device = resolve_device(device)
    robust = check_choice("errors", errors, ("sandwich", "crlb")) == "sandwich"
    # float32 ROIs go to the GPU as they are (half the transfer); the fit runs in float64
    single = device == "cuda" and data.dtype == np.float32
    data = np.ascontiguousarray(data, dtype=np.float32 if single else np.float64)
    start = np.zeros((n, len(PARAMS)))
    use_start = np.zeros(n, dtype=np.bool_)
    if init is not None:
        start = as_param_array(init, name="init")
        if start.shape[0] != n:
            raise ValueError(
                f"Expected `init` to have {n} rows (one per ROI), got {start.shape[0]}."
            )
        use_start = (
            np.all(np.isfinite(start), axis=1)
            & (start[:, 4] > 0)
            & (start[:, 5] > 0)
            & (np.abs(start[:, 6]) < 1)
        )
        start = np.ascontiguousarray(start)
    windows = check_windows(windows, n, (h, w))
    options = (code, s2, max_iter, tol)
    if windows is None:
        result = _fit_stack(data, start, use_start, *options, device)
    else:
        result = _in_windows(
            data, windows,
            lambda part, rows, window: _fit_stack(
                part, _in_window(start[rows], window), use_start[rows], *options,
                device if window == (0, h, 0, w) else "cpu",
            ),
        )  # fmt: skip
    if robust:
        return with_sandwich(result, data, method=method, readnoise=math.sqrt(s2), windows=windows)
    return result


def _fit_stack(
    data: np.ndarray,
    start: np.ndarray,
    use_start: np.ndarray,
    code: int,
    s2: float,
    max_iter: int,
    tol: float,
    device: str,
) -> FitResult:
    """The kernels' fits of every ROI of ``data`` (n, h, w), with the Cramér–Rao errors."""
    n, h, w = data.shape
    lower, upper = parameter_bounds((h, w), math.sqrt(s2))
    params = np.empty((n, len(PARAMS)))
    errors = np.empty((n, len(PARAMS)))
    loglik = np.empty(n)
    chi2 = np.empty(n)
    iterations = np.empty(n, dtype=np.int64)
    converged = np.empty(n, dtype=np.bool_)
    out = (params, errors, loglik, chi2, iterations, converged)
    if device == "cuda":
        from latentz.fit._cuda import fit_batch_cuda

        fit_batch_cuda(data, start, use_start, lower, upper, code, s2, max_iter, tol, out)
    else:
        data = np.ascontiguousarray(data, dtype=np.float64)
        # threads take the chunks one at a time: one slowed by other work holds up no other
        with one_thread_if(n < SMALL_BATCH), numba.parallel_chunksize(1):
            _kernels.fit_batch(
                data, start, use_start, lower, upper, code, s2, max_iter, tol,
                min(n, 64 * numba.get_num_threads()), *out,
            )  # fmt: skip
    correlations = np.full((n, len(CORRELATED)), np.nan)
    return FitResult(params, errors, loglik, chi2, iterations, converged, correlations)


def _in_window(params: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """Natural parameters (n, 7) with x, y moved from the whole ROI's pixels into ``window``'s."""
    moved = params.copy()
    moved[:, 0] -= window[2]
    moved[:, 1] -= window[0]
    return moved


def _failed(n: int) -> FitResult:
    """``n`` failed fits: NaN values, ``converged`` False, 0 iterations."""
    nan = np.full((n, len(PARAMS)), np.nan)
    return FitResult(nan, nan.copy(), np.full(n, np.nan), np.full(n, np.nan),
                     np.zeros(n, np.int64), np.zeros(n, bool),
                     np.full((n, len(CORRELATED)), np.nan))  # fmt: skip


def _in_windows(
    data: np.ndarray,
    windows: np.ndarray,
    fit: Callable[[np.ndarray, np.ndarray, tuple[int, int, int, int]], FitResult],
) -> FitResult:
    """``fit(pixels, rows, window)`` of each group of ROIs of ``data`` that share a window, on
    their window's pixels, assembled in ROI order with x, y in the whole ROI's pixels."""
    result = _failed(len(data))
    for rows, window in window_groups(windows):
        r0, r1, c0, c1 = window
        if min(r1 - r0, c1 - c0) < MIN_SIDE:
            continue
        part = fit(data[rows, r0:r1, c0:c1], rows, window)
        if c0 or r0:
            part.params[:, 0] += c0
            part.params[:, 1] += r0
        for whole, value in zip(result, part, strict=True):
            whole[rows] = value
    return result


def with_sandwich(
    result: FitResult,
    rois: np.ndarray,
    *,
    method: str,
    readnoise: float,
    windows: np.ndarray | None = None,
) -> FitResult:
    """``result`` of fitting ``rois`` (n, h, w, photoelectrons) with its errors replaced by the
    sandwich covariance's where that is usable, and its correlations (`CORRELATED`) set, as
    ``errors="sandwich"`` gives. For images of real PSFs (`latentz.localize`, full and tracking):
    a real PSF is not the Gaussian of eq. 1, and the sandwich holds the scatter that the
    Cramér–Rao bound understates (up to 1.6x near focus). "lsq" keeps the bound. ``windows``
    (n, 4), as in `fit_arrays`, are the pixels each fit saw."""
    if METHODS[method] == _kernels.LSQ:
        return result
    windows = check_windows(windows, len(rois), rois.shape[1:])
    if windows is None:
        cov = sandwich_batch(rois, result.params, readnoise)
    else:
        cov = np.full((len(rois), len(PARAMS), len(PARAMS)), np.nan)
        for rows, (r0, r1, c0, c1) in window_groups(windows):
            inside = _in_window(result.params[rows], (r0, r1, c0, c1))
            cov[rows] = sandwich_batch(rois[rows, r0:r1, c0:c1], inside, readnoise)
    variance = np.diagonal(cov, 0, 1, 2)
    usable = np.all(variance > 0, axis=1)
    errors = result.errors.copy()
    errors[usable] = np.sqrt(variance[usable])
    return result._replace(errors=errors, correlations=correlations_of(cov))


def replace_rows(result: FitResult, new: FitResult, rows: np.ndarray) -> FitResult:
    """``result`` with the fits at ``rows`` (boolean mask) replaced by ``new``'s, in order."""
    fields = []
    for old, value in zip(result, new, strict=True):
        out = old.copy()
        out[rows] = value
        fields.append(out)
    return FitResult(*fields)


def correlations_of(cov: np.ndarray) -> np.ndarray:
    """Correlations (n, 6) of the pairs `CORRELATED` in covariances (n, 7, 7) of `PARAMS`."""
    first = [PARAMS.index(a) for a, _ in CORRELATED]
    second = [PARAMS.index(b) for _, b in CORRELATED]
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.sqrt(np.diagonal(cov, 0, 1, 2))
        return cov[:, first, second] / (sd[:, first] * sd[:, second])


def result_table(result: FitResult, *, frame: Any = None, **after: Any) -> pd.DataFrame:
    """The columns `FIT_COLUMNS` of a `FitResult` as a DataFrame, after a ``frame`` column when
    one is given and before the columns ``after`` (name=values). Built in one step: inserting
    columns one by one costs milliseconds per table, the time of fitting hundreds of ROIs."""
    params = result.params
    columns = {} if frame is None else {"frame": frame}
    columns.update({name: params[:, k] for k, name in enumerate(PARAMS)})
    columns["photons"] = photons_of(params[:, 2], params[:, 4], params[:, 5], params[:, 6])
    columns.update({name: result.errors[:, k] for k, name in enumerate(ERROR_COLUMNS)})
    columns.update(loglik=result.loglik, chi2=result.chi2, iterations=result.iterations,
                   converged=result.converged)  # fmt: skip
    columns.update({name: result.correlations[:, k] for k, name in enumerate(CORRELATION_COLUMNS)})
    columns.update(after)
    return pd.DataFrame(columns)


def fit_rois(
    rois: Any,
    *,
    method: str = "mle",
    camera: Camera | None = None,
    init: Any = None,
    max_iter: int = 50,
    tol: float = 1e-2,
    device: str = "auto",
    errors: str = "crlb",
    windows: Any = None,
) -> pd.DataFrame:
    """Fit the bivariate Gaussian of eq. 1 to every ROI (Copeland et al. 2021).

    Parameters
    ----------
    rois : array_like (n, h, w)
        ROIs in photoelectrons if ``camera`` is None, else in ADU (converted with
        ``camera.to_photons``). h and w are at least 3.
    method : {"mle", "wlsq", "lsq"}
        ``"mle"``: Poisson maximum likelihood, read noise by ``d + s^2 ~ Poisson(mu + s^2)``.
        ``"wlsq"``: the paper's light-weighting, read here as least squares weighted by
        ``1 / (mu + readnoise^2)`` from the current model, recomputed after every accepted step
        (iterated); its fixed point is the Poisson maximum-likelihood estimate.
        ``"lsq"``: unweighted least squares.
    camera : Camera, optional
        Offset, gain and read noise. A camera with a flatfield is refused: a ROI does not know
        where it lies on the sensor, so convert whole frames first (as `localize` does).
    init : DataFrame or array_like (n, 7), optional
        Starting values (columns x, y, amplitude, background, wx, wy, rho); default moments.
    max_iter : int
        Maximum Levenberg–Marquardt iterations per ROI.
    tol : float
        Convergence tolerance: the fit's distance from the optimum in Cramér–Rao bounds.
    device : {"auto", "cpu", "cuda"}
        CPU or GPU (numba's CUDA target, extra ``latentz[gpu]``); "auto" uses a usable GPU.
    errors : {"crlb", "sandwich"}
        The ``*_err`` columns: see `fit_arrays`.
    windows : array_like (n, 4) of int, optional
        The pixels each fit sees, ``(row_start, row_stop, col_start, col_stop)``: see
        `fit_arrays`. Default: every ROI whole.

    Returns
    -------
    DataFrame
        One row per ROI, in ROI coordinates (pixel ``[i, j]`` centred at ``x = j, y = i``), with
        the columns `FIT_COLUMNS`: x, y, amplitude, background, wx, wy, rho, photons
        (``2 pi A wx wy sqrt(1 - rho^2)``), their standard deviations ``*_err`` (`FitResult`:
        the sandwich covariance, or the Cramér–Rao bound), loglik, chi2, iterations, converged
        and the correlations ``*_corr`` of the shape's parameters (`CORRELATION_COLUMNS`). A
        failed fit is returned with ``converged`` False.

    Examples
    --------
    >>> from latentz.fit import render_rois
    >>> truth = {"x": [5.3], "y": [4.8], "amplitude": [200.0], "background": [10.0],
    ...          "wx": [1.5], "wy": [1.2], "rho": [0.3]}
    >>> fit = fit_rois(render_rois(truth, shape=11))
    >>> round(float(fit["x"].iloc[0]), 6), bool(fit["converged"].iloc[0])
    (5.3, True)
    """
    readnoise = 0.0
    if camera is not None:
        if not isinstance(camera, Camera):
            raise TypeError(
                f"Expected `camera` to be a latentz Camera, got {type(camera).__name__}."
            )
        if camera.flatfield is not None:
            raise ValueError(
                "`camera` has a flatfield, but fit_rois cannot know where the ROIs lie on the "
                "sensor: convert frames with camera.to_photons first, or use localize."
            )
        rois = camera.to_photons(check_array("rois", rois, ndim=3, dtype_kind="uif"))
        readnoise = camera.readnoise
    result = fit_arrays(
        rois,
        method=method,
        readnoise=readnoise,
        init=init,
        max_iter=max_iter,
        tol=tol,
        device=device,
        errors=errors,
        windows=windows,
    )
    return result_table(result)

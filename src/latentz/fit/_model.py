"""The bivariate Gaussian of eq. 1, its parameterisation and its Fisher information (NumPy).

Eq. 1 of Copeland et al. (2021), sampled at pixel centres (pixel ``[i, j]`` at ``x = j, y = i``)::

    mu = A exp(-q / 2) + B,   q = (u^2 - 2 rho u v + v^2) / (1 - rho^2),
    u = (x_p - x') / wx,      v = (y_p - y') / wy.

Natural parameters, in this order everywhere (``PARAMS``): ``x, y, amplitude, background, wx, wy,
rho``; ``wx`` and ``wy`` are standard deviations in pixels. The fitters work in *internal*
parameters ``x, y, A, B, log wx, log wy, atanh rho``, which keep the widths positive and ``|rho|``
below 1. Everything here is plain NumPy, vectorised over ROIs: it renders ground truth, computes
Cramér–Rao bounds, and is the reference twin of the numba kernels in :mod:`._kernels`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.validate import check_array

__all__ = [
    "PARAMS",
    "render_rois",
    "photons_of",
    "amplitude_of",
    "model_and_jacobian",
    "fisher_information",
    "poisson_information",
    "crlb",
    "covariance",
    "moment_start",
]

#: Natural parameters of eq. 1, in the column order of every parameter array.
PARAMS = ("x", "y", "amplitude", "background", "wx", "wy", "rho")
N_PARAMS = len(PARAMS)


def photons_of(amplitude: Any, wx: Any, wy: Any, rho: Any) -> np.ndarray:
    """Integral of the Gaussian of eq. 1 over the plane: ``2 pi A wx wy sqrt(1 - rho^2)``.

    Parameters
    ----------
    amplitude : array_like
        Peak height ``A`` in photoelectrons per pixel.
    wx, wy : array_like
        Standard deviations in pixels.
    rho : array_like
        Correlation coefficient, ``|rho| < 1``.

    Returns
    -------
    ndarray
        Photoelectrons in the spot (the background excluded).
    """
    rho = np.asarray(rho, dtype=float)
    return (
        2.0
        * np.pi
        * np.asarray(amplitude)
        * np.asarray(wx)
        * np.asarray(wy)
        * np.sqrt(1.0 - rho**2)
    )


def amplitude_of(photons: Any, wx: Any, wy: Any, rho: Any) -> np.ndarray:
    """Peak height ``A`` of a spot holding ``photons`` photoelectrons (inverse of `photons_of`)."""
    return np.asarray(photons, dtype=float) / photons_of(1.0, wx, wy, rho)


def as_param_array(params: Any, *, name: str = "params") -> np.ndarray:
    """Return parameters as a float array (n, 7) in `PARAMS` order.

    ``params`` is an array (n, 7) or (7,), or a DataFrame / mapping with the columns of `PARAMS`;
    a table may give ``photons`` instead of ``amplitude``.
    """
    if isinstance(params, pd.DataFrame | dict):
        table = pd.DataFrame(params)
        if "amplitude" not in table and "photons" in table:
            table = table.assign(
                amplitude=amplitude_of(table["photons"], table["wx"], table["wy"], table["rho"])
            )
        missing = [c for c in PARAMS if c not in table]
        if missing:
            raise ValueError(f"`{name}` is missing column(s) {', '.join(missing)}.")
        array = table[list(PARAMS)].to_numpy(dtype=np.float64)
    else:
        array = check_array(name, params, ndim=(1, 2), dtype_kind="uif").astype(np.float64)
        array = np.atleast_2d(array)
        if array.shape[1] != N_PARAMS:
            raise ValueError(
                f"Expected `{name}` to have shape (n, {N_PARAMS}) in the order {PARAMS}, "
                f"got {array.shape}."
            )
    return array


def _pixel_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.indices(shape, dtype=np.float64)
    return cols.ravel(), rows.ravel()


def model_and_jacobian(
    params: np.ndarray, shape: tuple[int, int], *, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Expected counts and their derivatives with respect to the *internal* parameters.

    Parameters
    ----------
    params : ndarray (n, 7)
        Natural parameters in `PARAMS` order.
    shape : (h, w)
        ROI shape in pixels.

    Returns
    -------
    mu : ndarray (n, h*w)
        Eq. 1 at the pixel centres, row-major.
    jac : ndarray (n, h*w, 7) or None
        d mu / d (x, y, A, B, log wx, log wy, atanh rho); None unless ``jacobian``.
    """
    xp, yp = _pixel_grid(shape)
    x, y, amp, bg, wx, wy, rho = (params[:, k, None] for k in range(N_PARAMS))
    om = 1.0 - rho**2
    u = (xp - x) / wx
    v = (yp - y) / wy
    a = (u - rho * v) / om
    b = (v - rho * u) / om
    q = u * a + v * b
    g = np.exp(-0.5 * q)
    ag = amp * g
    if not jacobian:
        return ag + bg, None
    jac = np.stack(
        [
            ag * a / wx,
            ag * b / wy,
            g,
            np.ones_like(g),
            ag * u * a,
            ag * v * b,
            ag * (u * v - rho * q),
        ],
        axis=-1,
    )
    return ag + bg, jac


def render_rois(params: Any, *, shape: tuple[int, int] | int) -> np.ndarray:
    """Render eq. 1 (expected photoelectrons, no noise) for each row of a parameter table.

    Parameters
    ----------
    params : DataFrame or array_like (n, 7)
        Columns x, y (ROI pixels), amplitude (or photons), background, wx, wy (px), rho.
    shape : int or (h, w)
        ROI shape in pixels; an int gives a square ROI.

    Returns
    -------
    ndarray (n, h, w)
        Expected photoelectrons per pixel, sampled at pixel centres.

    Examples
    --------
    >>> roi = render_rois({"x": [2.0], "y": [2.0], "amplitude": [10.0], "background": [1.0],
    ...                    "wx": [1.0], "wy": [1.0], "rho": [0.0]}, shape=5)
    >>> float(roi[0, 2, 2])
    11.0
    """
    array = as_param_array(params)
    hw = _check_shape(shape)
    if np.any(array[:, 4:6] <= 0) or np.any(np.abs(array[:, 6]) >= 1):
        raise ValueError("Expected wx, wy > 0 and |rho| < 1 in `params`.")
    mu, _ = model_and_jacobian(array, hw, jacobian=False)
    return mu.reshape(len(array), *hw)


def _check_shape(shape: tuple[int, int] | int) -> tuple[int, int]:
    hw = (shape, shape) if isinstance(shape, int | np.integer) else tuple(shape)
    if len(hw) != 2 or any(int(s) < 1 for s in hw):
        raise ValueError(f"Expected `shape` to be a positive int or (h, w), got {shape!r}.")
    return int(hw[0]), int(hw[1])


def fisher_information(
    params: Any, *, shape: tuple[int, int] | int, readnoise: float = 0.0
) -> np.ndarray:
    """Fisher information of eq. 1 in the *natural* parameters, per ROI.

    The noise model is Poisson shot noise plus Gaussian read noise, approximated as
    ``data + readnoise^2 ~ Poisson(mu + readnoise^2)``, so
    ``I = sum_pixels grad(mu) grad(mu)^T / (mu + readnoise^2)``.

    Returns
    -------
    ndarray (n, 7, 7)
    """
    array = as_param_array(params)
    mu, jac = model_and_jacobian(array, _check_shape(shape))
    scale = np.stack(
        [np.ones(len(array))] * 4 + [array[:, 4], array[:, 5], 1.0 - array[:, 6] ** 2], axis=1
    )
    return poisson_information(jac / scale[:, None, :], mu, readnoise=readnoise)


def poisson_information(
    jacobian: np.ndarray, mu: np.ndarray, *, readnoise: float = 0.0
) -> np.ndarray:
    """Fisher information ``sum_pixels grad(mu) grad(mu)^T / (mu + readnoise^2)`` per ROI, of
    any model: ``jacobian`` (n, pixels, k) d mu / d parameter, ``mu`` (n, pixels) the expected
    photoelectrons, read noise as a Poisson shift (`fisher_information`'s noise model);
    returns (n, k, k)."""
    weights = 1.0 / (mu + readnoise**2)
    return np.matmul((jacobian * weights[:, :, None]).transpose(0, 2, 1), jacobian)


def crlb(params: Any, *, shape: tuple[int, int] | int, readnoise: float = 0.0) -> np.ndarray:
    """Cramér–Rao lower bounds (standard deviations) of the natural parameters, per ROI.

    Returns
    -------
    ndarray (n, 7)
        Bounds on x, y (px), amplitude, background (photoelectrons), wx, wy (px) and rho; NaN
        where the Fisher information is singular.
    """
    info = fisher_information(params, shape=shape, readnoise=readnoise)
    out = np.full(info.shape[:2], np.nan)
    for k, matrix in enumerate(info):
        try:
            out[k] = np.sqrt(np.diag(np.linalg.inv(matrix)))
        except np.linalg.LinAlgError:
            continue
    return out


def covariance(
    params: Any,
    *,
    shape: tuple[int, int] | int,
    readnoise: float = 0.0,
    max_condition: float = 1e12,
) -> np.ndarray:
    """Inverse Fisher information (n, 7, 7) of the natural parameters, per ROI: the Cramér–Rao
    covariance; NaN where the information's condition number is ``max_condition`` or more.

    The information is that of :func:`fisher_information`, computed by the numba kernel
    (:func:`._kernels.fisher_batch`, the same sums in one pass per ROI: calibration asks for
    it at every image)."""
    import numba

    from latentz.fit._kernels import fisher_batch

    array = np.ascontiguousarray(as_param_array(params), dtype=np.float64)
    h, w = _check_shape(shape)
    info = np.empty((len(array), N_PARAMS, N_PARAMS))
    if len(array):
        fisher_batch(array, h, w, float(readnoise) ** 2,
                     min(len(array), 64 * numba.get_num_threads()), info)  # fmt: skip
    out = np.full(info.shape, np.nan)
    usable = np.all(np.isfinite(info), axis=(1, 2))
    # the information is symmetric: its condition number is that of its eigenvalues (the SVD
    # of np.linalg.cond costs as much as the information itself)
    eig = np.abs(np.linalg.eigvalsh(info[usable]))
    with np.errstate(divide="ignore", invalid="ignore"):
        usable[usable] = eig.max(axis=1) / eig.min(axis=1) < max_condition
    out[usable] = np.linalg.inv(info[usable])
    return out


def moment_start(rois: np.ndarray, peaks: np.ndarray | None = None) -> np.ndarray:
    """Starting values (n, 7) from image moments; the NumPy twin of the kernels' start.

    The background is the mean of the ROI's border pixels. The peak is the brightest pixel of the
    3 x 3 box-filtered, background-subtracted ROI, or the pixel ``peaks`` (n, 2) gives as
    (row, col) in ROI pixels (a detection's maximum: a brighter neighbour in the ROI does not draw
    the start to itself); the position is the centroid of the positive signal in the 3 x 3
    neighbourhood of that pixel; rho and the aspect ratio come from the second moments of the
    positive signal, and the width scale from the total signal divided by the peak
    (``photons = 2 pi A wx wy sqrt(1 - rho^2)``), which noise inflates far less than moments do.
    """
    n, h, w = rois.shape
    border = np.concatenate(
        [rois[:, 0, :], rois[:, -1, :], rois[:, 1:-1, 0], rois[:, 1:-1, -1]], axis=1
    )
    bg = border.mean(axis=1)
    sig = rois - bg[:, None, None]
    padded = np.pad(sig, ((0, 0), (1, 1), (1, 1)))
    box = sum(padded[:, di : di + h, dj : dj + w] for di in range(3) for dj in range(3))
    if peaks is None:
        i0, j0 = np.divmod(box.reshape(n, -1).argmax(axis=1), w)
    else:
        i0, j0 = np.asarray(peaks, np.int64).T
    idx = np.arange(n)
    peak = np.maximum(sig[idx, i0, j0], box[idx, i0, j0] / 9.0)
    pos = np.clip(sig, 0.0, None)
    rows, cols = np.indices((h, w), dtype=np.float64)
    near = (np.abs(rows[None] - i0[:, None, None]) <= 1) & (
        np.abs(cols[None] - j0[:, None, None]) <= 1
    )
    wn = pos * near
    total_n = wn.sum(axis=(1, 2))
    ok = total_n > 0
    safe = np.where(ok, total_n, 1.0)
    x0 = np.where(ok, (wn * cols).sum(axis=(1, 2)) / safe, j0)
    y0 = np.where(ok, (wn * rows).sum(axis=(1, 2)) / safe, i0)
    total = pos.sum(axis=(1, 2))
    safe_t = np.where(total > 0, total, 1.0)
    dx = cols[None] - x0[:, None, None]
    dy = rows[None] - y0[:, None, None]
    vxx = (pos * dx * dx).sum(axis=(1, 2)) / safe_t
    vyy = (pos * dy * dy).sum(axis=(1, 2)) / safe_t
    vxy = (pos * dx * dy).sum(axis=(1, 2)) / safe_t
    return _finish_start(x0, y0, peak, bg, sig.sum(axis=(1, 2)), vxx, vyy, vxy, h, w)


def _finish_start(x0, y0, peak, bg, signal, vxx, vyy, vxy, h, w):
    """Shared arithmetic of the moment start (also written out in the kernel)."""
    wmax = 0.5 * min(h, w)
    good = (vxx > 0) & (vyy > 0)
    rho = np.where(good, vxy / np.sqrt(np.where(good, vxx * vyy, 1.0)), 0.0)
    rho = np.clip(rho, -0.8, 0.8)
    aspect = np.where(good, np.sqrt(np.where(good, vxx / np.where(good, vyy, 1.0), 1.0)), 1.0)
    aspect = np.clip(aspect, 0.5, 2.0)
    amp = np.maximum(peak, 1e-3)
    area = np.maximum(signal, amp) / (2.0 * np.pi * amp * np.sqrt(1.0 - rho**2))
    area = np.clip(area, 0.25, wmax * wmax)
    wx = np.clip(np.sqrt(area * aspect), 0.5, wmax)
    wy = np.clip(np.sqrt(area / aspect), 0.5, wmax)
    return np.stack([x0, y0, amp, bg, wx, wy, rho], axis=1).astype(np.float64)

"""Cramér–Rao-propagated z precision of the calibration's PSF for emitters of any brightness.

The calibration particles are bright; single molecules hold 100–10,000 photons. For each
calibration image (particle × plane) the fit's Cramér–Rao bounds on (wx, wy, ρ, A) are computed
for an emitter of ``photons`` photons with the same widths, ρ and background, propagated to the
shape value s (:func:`~latentz.calibration.shape.shape_sigma`) and through the local slope of
s(z): ``σ_z = σ_s / |ds/dz|``. Where the PSF changes little with z (far from focus, ring images)
this σ_z grows large, whatever the calibration particles' own residuals say.
"""

from __future__ import annotations

import numpy as np

from latentz.calibration.local import LocalModels
from latentz.calibration.shape import shape_sigma, uses_amplitude
from latentz.calibration.traces import Traces
from latentz.fit._model import amplitude_of, covariance

__all__ = ["image_crlb", "crlb_sigma_z"]


def image_crlb(
    traces: Traces, photons: float, *, roi_size: int, readnoise: float = 0.0
) -> dict[str, np.ndarray]:
    """Cramér–Rao bounds (n, n_z) on ``wx``, ``wy`` (px), ``rho`` and ``amplitude`` (photons
    per px at the peak) of an emitter of ``photons`` photons imaged like each calibration image
    (same widths, ρ and background, centred in a ROI of ``roi_size`` px); also its ``amplitude``.
    NaN where a trace value is missing or the Fisher information is singular."""
    wx, wy, rho, bg = (traces[k] for k in ("wx", "wy", "rho", "background"))
    amplitude = amplitude_of(photons, wx, wy, rho)
    centre = np.full(wx.shape, (roi_size - 1) / 2.0)
    params = np.stack([centre, centre, amplitude, bg, wx, wy, rho], axis=-1).reshape(-1, 7)
    finite = np.all(np.isfinite(params), axis=1)
    bounds = np.full(params.shape, np.nan)
    if finite.any():
        cov = covariance(params[finite], shape=roi_size, readnoise=readnoise)
        bounds[finite] = np.sqrt(np.abs(np.diagonal(cov, axis1=1, axis2=2)))
    bounds = bounds.reshape(*wx.shape, 7)
    return {
        "amplitude": amplitude,
        "amplitude_err": bounds[..., 2],
        "wx_err": bounds[..., 4],
        "wy_err": bounds[..., 5],
        "rho_err": bounds[..., 6],
    }


def crlb_sigma_z(
    local: LocalModels,
    traces: Traces,
    shape: str,
    photons: float,
    *,
    roi_size: int,
    readnoise: float = 0.0,
    bounds: dict[str, np.ndarray] | None = None,
) -> np.ndarray:
    """σ_z (nm, (n, n_z)) of an emitter of ``photons`` photons at each calibration plane, from
    the Cramér–Rao bounds of its fit (``bounds``: :func:`image_crlb`, computed if not given),
    for ``shape``; NaN outside the shape's monotonic range. For the A-normalised shapes the
    emitter's own A_{ρ=ρ0} is taken as known (its brightness relative to the calibration's is
    a systematic error, not counted here)."""
    if bounds is None:
        bounds = image_crlb(traces, photons, roi_size=roi_size, readnoise=readnoise)
    model = local.shapes[shape]
    wx, wy, rho = traces["wx"], traces["wy"], traces["rho"]
    amplitude = bounds["amplitude"]
    ref = None
    if uses_amplitude(shape):  # the same A_n as the calibration image: A_ref scales with A
        ref = amplitude * model.amplitude_ref[:, None] / traces["amplitude"]
    errors = tuple(bounds[k] for k in ("wx_err", "wy_err", "rho_err", "amplitude_err"))
    sigma_s = shape_sigma(
        shape, wx, wy, rho, amplitude, errors, theta=local.theta, amplitude_ref=ref
    )
    slope = np.abs(model.forward.derivative()(local.z_nm))
    low, high = model.z_range.T
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = (local.z_nm >= low[:, None]) & (local.z_nm <= high[:, None])
        return np.where(inside, sigma_s / slope, np.nan)


#: Photon count of the reference emitter that defines the usable range (the geometric middle
#: of single molecules' 100–10,000 photons).
REFERENCE_PHOTONS = 1000.0
#: A plane is usable while the reference emitter's σ_z stays within this factor of its best.
USABLE_FACTOR = 4.0
_SMOOTH_PLANES = 5


def usable_planes(sigma_z: np.ndarray) -> np.ndarray:
    """(n, n_z) mask: the contiguous run of planes around each particle's best (smallest)
    σ_z where σ_z (nm, (n, n_z); smoothed by a running median of 5 planes) stays at most
    :data:`USABLE_FACTOR` times that best. Outside it the PSF hardly changes with z (far
    defocus, ring images) and z is unreliable even where the shape is still monotonic."""
    from scipy.ndimage import median_filter

    filled = np.where(np.isfinite(sigma_z), sigma_z, np.inf)
    smooth = median_filter(filled, size=(1, _SMOOTH_PLANES), mode="nearest")
    best = np.min(smooth, axis=1)
    ok = smooth <= USABLE_FACTOR * best[:, None]
    n, n_z = ok.shape
    idx = np.arange(n_z)
    centre = np.argmin(smooth, axis=1)
    bad = ~ok
    left = np.max(np.where(bad & (idx < centre[:, None]), idx, -1), axis=1) + 1
    right = np.min(np.where(bad & (idx > centre[:, None]), idx, n_z), axis=1) - 1
    mask = (idx >= left[:, None]) & (idx <= right[:, None]) & np.isfinite(sigma_z)
    return mask & np.isfinite(best)[:, None]

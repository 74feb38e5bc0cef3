"""Shape parameters for axial localization (paper eqs. 4–6, and the "auto" pair).

The paper's microscope has its intrinsic astigmatism at π/4 to the camera axes, so the correlation
coefficient ρ of the bivariate Gaussian (eq. 1) carries it:

- ``"rho"``: ρ;
- ``"rho_w"``: ρ_w = ρ (|w_x| + |w_y|) / 2 (eq. 4), independent of emission intensity;
- ``"rho_A"``: ρ_A = ρ / A_n with A_n = A / A_{ρ=ρ0} (eqs. 5–6), ρ0 the minimum |ρ| of the
  calibration trace.

Astigmatism can lie at any angle θ (a cylindrical lens puts it at 0, where ρ ≈ 0 and w_x − w_y
carries it). With the image covariance ``[[wx², ρ wx wy], [ρ wx wy, wy²]]`` the ellipticity
components are ``e1 = (wx² − wy²) / (wx² + wy²)`` and ``e2 = 2 ρ wx wy / (wx² + wy²)``; the
projection on the astigmatism axis is ``e_θ = e1 cos 2θ + e2 sin 2θ``. Then

- ``"auto"``: e_θ (|w_x| + |w_y|) / 2, scaled like ρ_w (intensity independent);
- ``"auto_A"``: e_θ / A_n with A_n normalised at the minimum |e_θ|, like ρ_A.

At θ = π/4 and w_x ≈ w_y, e_θ ≈ ρ, so "auto" and "auto_A" reduce to ρ_w and ρ_A.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "SHAPES",
    "ellipticity",
    "astigmatism_angle",
    "shape_value",
    "shape_sigma",
    "reference_amplitude",
    "uses_amplitude",
]

SHAPES = ("rho", "rho_w", "rho_A", "auto", "auto_A")


def uses_amplitude(shape: str) -> bool:
    """Whether ``shape`` is normalised by A_n (and so needs a reference amplitude)."""
    return shape in ("rho_A", "auto_A")


def ellipticity(wx: Any, wy: Any, rho: Any) -> tuple[np.ndarray, np.ndarray]:
    """Ellipticity components (e1, e2) of the Gaussian's covariance, each in [-1, 1]."""
    wx2 = np.square(np.asarray(wx, dtype=np.float64))
    wy2 = np.square(np.asarray(wy, dtype=np.float64))
    total = wx2 + wy2
    e1 = (wx2 - wy2) / total
    e2 = 2.0 * np.asarray(rho, dtype=np.float64) * np.sqrt(wx2 * wy2) / total
    return e1, e2


def astigmatism_angle(wx: Any, wy: Any, rho: Any) -> float:
    """Estimate the astigmatism angle θ (rad) from through-focus fits.

    The long axis of the image lies at θ on one side of focus and at θ + π/2 on the other, so the
    ellipticity ``E = e1 + i e2 = |E| exp(2 i φ)`` has ``E²`` pointing at 4θ on both sides. The
    sum of ``E²`` over all planes and particles weights each image by ``|E|²``, so images far from
    focus dominate and the noisy round images near focus hardly count. θ is defined modulo π/2
    and returned in [−π/8, 3π/8), so that a π/4 microscope gives π/4 (e_θ = e2 ≈ ρ) and a
    cylindrical lens gives 0 (e_θ = e1).
    """
    e1, e2 = ellipticity(wx, wy, rho)
    spin2 = (e1 + 1j * e2).ravel()
    spin2 = spin2[np.isfinite(spin2)]
    if spin2.size == 0:
        raise ValueError("Cannot estimate the astigmatism angle: no finite width/ρ values.")
    total = np.sum(spin2**2)
    if abs(total) == 0:
        raise ValueError("Cannot estimate the astigmatism angle: the images are all round.")
    theta = np.angle(total) / 4.0
    return float((theta + np.pi / 8) % (np.pi / 2) - np.pi / 8)


def _base(shape: str, wx: np.ndarray, wy: np.ndarray, rho: np.ndarray, theta: float | None):
    """ρ for the paper's parameters, e_θ for the auto pair."""
    if shape in ("rho", "rho_w", "rho_A"):
        return rho
    if theta is None:
        raise ValueError(f"shape={shape!r} needs the astigmatism angle `theta`.")
    e1, e2 = ellipticity(wx, wy, rho)
    return e1 * np.cos(2 * theta) + e2 * np.sin(2 * theta)


def reference_amplitude(
    shape: str, wx: Any, wy: Any, rho: Any, amplitude: Any, *, theta: float | None = None
) -> np.ndarray:
    """A_{ρ=ρ0} of each trace: the amplitude of the image with the minimum |ρ| (or |e_θ|).

    Arrays have shape (..., n_z); the minimum is taken along the last axis, ignoring NaN.
    """
    wx, wy, rho, amp = (np.asarray(a, dtype=np.float64) for a in (wx, wy, rho, amplitude))
    base = np.abs(_base(shape, wx, wy, rho, theta))
    base = np.where(np.isfinite(base) & np.isfinite(amp), base, np.inf)
    idx = np.argmin(base, axis=-1)
    ref = np.take_along_axis(amp, idx[..., None], axis=-1)[..., 0]
    return np.where(np.all(np.isinf(base), axis=-1), np.nan, ref)


def shape_value(
    shape: str,
    wx: Any,
    wy: Any,
    rho: Any,
    amplitude: Any = None,
    *,
    theta: float | None = None,
    amplitude_ref: Any = None,
) -> np.ndarray:
    """The shape parameter ``shape`` (one of :data:`SHAPES`) of fitted images.

    ``amplitude`` and ``amplitude_ref`` (A_{ρ=ρ0}, broadcast against ``amplitude``) are needed
    for "rho_A" and "auto_A"; ``theta`` (rad) for "auto" and "auto_A".
    """
    if shape not in SHAPES:
        raise ValueError(f"Expected `shape` to be one of {SHAPES}, got {shape!r}.")
    wx, wy, rho = (np.asarray(a, dtype=np.float64) for a in (wx, wy, rho))
    base = _base(shape, wx, wy, rho, theta)
    if shape == "rho":
        return base
    if shape in ("rho_w", "auto"):
        return base * (np.abs(wx) + np.abs(wy)) / 2.0
    if amplitude is None or amplitude_ref is None:
        raise ValueError(f"shape={shape!r} needs `amplitude` and `amplitude_ref`.")
    amp_n = np.asarray(amplitude, dtype=np.float64) / np.asarray(amplitude_ref, dtype=np.float64)
    return base / amp_n


def shape_sigma(
    shape: str,
    wx: Any,
    wy: Any,
    rho: Any,
    amplitude: Any,
    errors: tuple[Any, Any, Any, Any],
    *,
    theta: float | None = None,
    amplitude_ref: Any = None,
) -> np.ndarray:
    """1σ uncertainty of the shape parameter, propagated from the fit's (wx, wy, rho, amplitude)
    uncertainties ``errors`` to first order (central differences; covariances neglected)."""
    params = [np.asarray(a, dtype=np.float64) for a in (wx, wy, rho, amplitude)]
    variance = np.zeros(np.broadcast_shapes(*(p.shape for p in params)))
    for i, err in enumerate(errors):
        err = np.asarray(err, dtype=np.float64)
        step = np.maximum(np.abs(err), 1e-9) * 1e-3
        hi = [p + step if j == i else p for j, p in enumerate(params)]
        lo = [p - step if j == i else p for j, p in enumerate(params)]
        grad = (
            shape_value(shape, *hi, theta=theta, amplitude_ref=amplitude_ref)
            - shape_value(shape, *lo, theta=theta, amplitude_ref=amplitude_ref)
        ) / (2 * step)
        variance = variance + np.square(grad * err)
    return np.sqrt(variance)

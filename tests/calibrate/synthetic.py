"""Analytic through-focus traces of astigmatic Gaussian images, with known truth.

An astigmatic image has principal widths ``σ1 = s0 sqrt(1 + ((z − z_f − c)/d)²)`` and
``σ2 = s0 sqrt(1 + ((z − z_f + c)/d)²)`` along axes at θ and θ + π/2, so its covariance is
``R(θ) diag(σ1², σ2²) R(θ)ᵀ``; (wx, wy, ρ) follow from it, and A = N / (2π σ1 σ2). Noise of
the fitted parameters is Gaussian with the standard deviations a Gaussian fit reaches without
background (σ_x = w/√N, σ_w = w/√(2N), σ_ρ = (1 − ρ²)/√N, σ_A = A √(2/N)), scaled by ``noise``.
"""

from __future__ import annotations

import numpy as np

from latentz.calibrate.traces import Traces


def widths(z, z_f, *, theta, s0=1.5, c=400.0, d=600.0):
    """(wx, wy, rho, sigma1, sigma2) of the noise-free image at piezo z."""
    s1 = s0 * np.sqrt(1 + ((z - z_f - c) / d) ** 2)
    s2 = s0 * np.sqrt(1 + ((z - z_f + c) / d) ** 2)
    ct, st = np.cos(theta), np.sin(theta)
    sxx = ct**2 * s1**2 + st**2 * s2**2
    syy = st**2 * s1**2 + ct**2 * s2**2
    sxy = ct * st * (s1**2 - s2**2)
    wx, wy = np.sqrt(sxx), np.sqrt(syy)
    return wx, wy, sxy / (wx * wy), s1, s2


def make_traces(
    n=40,
    *,
    z_nm=None,
    theta=np.pi / 4,
    photons=20000.0,
    noise=1.0,
    z_f=None,
    positions=None,
    seed=0,
    shift_nm_per_um=0.05,
):
    """Traces of ``n`` particles; returns (Traces, truth dict)."""
    rng = np.random.default_rng(seed)
    z = np.arange(-3000.0, 3000.1, 50.0) if z_nm is None else np.asarray(z_nm, float)
    zf = rng.uniform(-150, 150, n) if z_f is None else np.asarray(z_f, float)
    pos = rng.uniform(0, 500, (n, 2)) if positions is None else np.asarray(positions, float)
    zz = z[None, :] - zf[:, None]
    wx, wy, rho, s1, s2 = widths(z[None, :], zf[:, None], theta=theta)
    amp = photons / (2 * np.pi * s1 * s2)
    # apparent lateral motion: a smooth cubic in z, in pixels
    dx = shift_nm_per_um * (zz / 1000) + 0.02 * (zz / 1000) ** 3
    dy = -0.5 * shift_nm_per_um * (zz / 1000) + 0.01 * (zz / 1000) ** 2
    sd = {
        "x": wx / np.sqrt(photons),
        "y": wy / np.sqrt(photons),
        "wx": wx / np.sqrt(2 * photons),
        "wy": wy / np.sqrt(2 * photons),
        "rho": (1 - rho**2) / np.sqrt(photons),
        "amplitude": amp * np.sqrt(2 / photons),
    }
    true = {
        "x": pos[:, :1] + dx,
        "y": pos[:, 1:] + dy,
        "wx": wx,
        "wy": wy,
        "rho": rho,
        "amplitude": amp,
    }
    data = {k: v + noise * sd[k] * rng.standard_normal(v.shape) for k, v in true.items()}
    data["background"] = np.full_like(amp, 10.0)
    data.update({f"{k}_err": np.broadcast_to(sd[k], amp.shape).copy() for k in sd})
    truth = {"z_f": zf, "positions": pos, "true": true, "sd": sd, "dx": dx, "dy": dy}
    return Traces(z, data), truth

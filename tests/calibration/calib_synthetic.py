"""Analytic through-focus traces of astigmatic Gaussian images, with known truth.

An astigmatic image has principal widths ``σ1 = s0 sqrt(1 + ((z − z_f − c)/d)²)`` and
``σ2 = s0 sqrt(1 + ((z − z_f + c)/d)²)`` along axes at θ and θ + π/2, so its covariance is
``R(θ) diag(σ1², σ2²) R(θ)ᵀ``; (wx, wy, ρ) follow from it, and A = N / (2π σ1 σ2). Noise of
the fitted parameters is Gaussian with the standard deviations a Gaussian fit reaches without
background (σ_x = w/√N, σ_w = w/√(2N), σ_ρ = (1 − ρ²)/√N, σ_A = A √(2/N)), scaled by ``noise``.
"""

from __future__ import annotations

import numpy as np

from latentz.calibration.traces import Traces


def widths(z, z_f, *, theta, s0=1.5, c=500.0, d=1200.0):
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
    defect=None,
    noise_seed=None,
    c_nm=None,
):
    """Traces of ``n`` particles; returns (Traces, truth dict).

    ``noise_seed`` draws the noise from its own generator (same particles, new noise).
    ``defect`` (n,) of "none", "dimer" (two touching particles 2 s0 apart at a random angle:
    twice the photons, the image stretched along the pair) or "large" (1.5 s0, 4x the photons).
    ``c_nm`` (n,): each particle's astigmatic half-separation ``c`` (default 500 nm for all).
    """
    rng = np.random.default_rng(seed)
    z = np.arange(-3000.0, 3000.1, 50.0) if z_nm is None else np.asarray(z_nm, float)
    zf = rng.uniform(-150, 150, n) if z_f is None else np.asarray(z_f, float)
    pos = rng.uniform(0, 500, (n, 2)) if positions is None else np.asarray(positions, float)
    zz = z[None, :] - zf[:, None]
    kind = np.full(n, "none") if defect is None else np.asarray(defect)
    s0 = np.where(kind == "large", 2.25, 1.5)[:, None]
    c = np.full(n, 500.0) if c_nm is None else np.asarray(c_nm, float)
    wx, wy, rho, s1, s2 = widths(z[None, :], zf[:, None], theta=theta, s0=s0, c=c[:, None])
    n_ph = photons * np.select([kind == "dimer", kind == "large"], [2.0, 4.0], 1.0)[:, None]
    amp = n_ph / (2 * np.pi * s1 * s2)
    phi = rng.uniform(0, np.pi, n)[:, None]
    half = np.where(kind == "dimer", 1.5, 0.0)[:, None]  # half the separation, px
    sxx = wx**2 + (half * np.cos(phi)) ** 2
    syy = wy**2 + (half * np.sin(phi)) ** 2
    sxy = rho * wx * wy + half**2 * np.cos(phi) * np.sin(phi)
    det = sxx * syy - sxy**2
    amp = amp * np.sqrt(s1**2 * s2**2 / det)  # same photons spread over the larger image
    wx, wy, rho = np.sqrt(sxx), np.sqrt(syy), sxy / np.sqrt(sxx * syy)
    photons = n_ph
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
    noise_rng = rng if noise_seed is None else np.random.default_rng(noise_seed)
    data = {k: v + noise * sd[k] * noise_rng.standard_normal(v.shape) for k, v in true.items()}
    data["background"] = np.full_like(amp, 10.0)
    data.update({f"{k}_err": np.broadcast_to(sd[k], amp.shape).copy() for k in sd})
    truth = {
        "z_f": zf,
        "positions": pos,
        "true": true,
        "sd": sd,
        "dx": dx,
        "dy": dy,
        "defect": kind,
    }
    return Traces(z, data), truth

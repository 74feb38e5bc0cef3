"""Image formation: emitter patches added into frames, then the camera (shot noise, read noise,
offset, gain, 16-bit saturation).

PSFs are computed once per emitter and plane on a small patch around the emitter (never per
pixel of the frame), batched over planes, and added into the expected image in photoelectrons.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd
from scipy.fft import next_fast_len

from latentz.camera import Camera
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.optics import Optics

ADU_MAX = 65535


def patch_size_px(optics: Optics, max_abs_defocus_nm: float, diameter_nm: float) -> int:
    """Side of a square patch that holds the image of an emitter out to the edge of its
    geometric blur (defocus × tan θ), the particle radius and four Gaussian σ, plus 3 pixels."""
    reach_nm = (
        abs(max_abs_defocus_nm) * optics.max_ray_slope
        + diameter_nm / 2.0
        + 4.0 * optics.gaussian_sigma_nm
    )
    half = math.ceil(reach_nm / optics.pixel_size_nm) + 3
    return int(next_fast_len(2 * half))


def render_patches(
    optics: Optics,
    aberrations: AberrationMap,
    *,
    x: np.ndarray,
    y: np.ndarray,
    field_x: np.ndarray,
    field_y: np.ndarray,
    defocus_nm: np.ndarray,
    diameter_nm: float,
    size: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free images (fraction of photons per pixel) of ``n`` emitter instances.

    ``x, y`` are positions in frame pixels, ``field_x, field_y`` the same in full-field pixels
    (for the aberrations), ``defocus_nm`` the emitter's axial position relative to the focal plane.
    Returns patches (n, size, size) and their origins (n, 2) as (row, column) in frame pixels.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    defocus = np.asarray(defocus_nm, dtype=np.float64)
    coef = aberrations.at(field_x, field_y).reshape(-1, len(aberrations.modes))
    if np.all(coef == coef[:1]):
        coef = coef[:1]
    waves = np.tensordot(coef, optics.zernike_basis(aberrations.modes), axes=1)
    col0 = np.floor(x).astype(np.int64) - size // 2 + 1
    row0 = np.floor(y).astype(np.int64) - size // 2 + 1
    centers = np.stack([x - col0, y - row0], axis=1)
    patches = optics.render_batch(waves, defocus, centers, (size, size), diameter_nm)
    return patches, np.stack([row0, col0], axis=1)


def add_patches(
    frames: np.ndarray,
    frame_index: np.ndarray,
    patches: np.ndarray,
    origins: np.ndarray,
    weights: np.ndarray,
) -> None:
    """Add ``weights[k] * patches[k]`` into ``frames[frame_index[k]]`` at ``origins[k]``, clipped
    at the frame edges."""
    height, width = frames.shape[1:]
    size_r, size_c = patches.shape[1:]
    for k in range(len(patches)):
        r0, c0 = (int(v) for v in origins[k])
        r_lo, c_lo = max(r0, 0), max(c0, 0)
        r_hi, c_hi = min(r0 + size_r, height), min(c0 + size_c, width)
        if r_lo >= r_hi or c_lo >= c_hi:
            continue
        frames[frame_index[k], r_lo:r_hi, c_lo:c_hi] += (
            weights[k] * patches[k, r_lo - r0 : r_hi - r0, c_lo - c0 : c_hi - c0]
        )


def render_expected(
    emitters: pd.DataFrame,
    *,
    n_frames: int,
    frame_shape: tuple[int, int],
    origin: tuple[int, int],
    optics: Optics,
    aberrations: AberrationMap,
    background: float,
) -> np.ndarray:
    """Expected photoelectrons per pixel, (n_frames, H, W), before the camera.

    ``emitters`` has one row per emitter instance (emitter and frame): columns ``emitter``,
    ``frame``, ``x``, ``y`` (frame pixels), ``defocus_nm``, ``photons``, ``diameter_nm``. Rows of
    one emitter are rendered in one batch; ``origin`` (row, column) places the frame in the field.
    """
    expected = np.full((n_frames, *frame_shape), float(background), dtype=np.float64)
    for _, group in emitters.groupby("emitter", sort=False):
        diameter = float(group["diameter_nm"].iloc[0])
        defocus = group["defocus_nm"].to_numpy(np.float64)
        size = patch_size_px(optics, float(np.max(np.abs(defocus))), diameter)
        x = group["x"].to_numpy(np.float64)
        y = group["y"].to_numpy(np.float64)
        patches, origins = render_patches(
            optics,
            aberrations,
            x=x,
            y=y,
            field_x=x + origin[1],
            field_y=y + origin[0],
            defocus_nm=defocus,
            diameter_nm=diameter,
            size=size,
        )
        add_patches(
            expected,
            group["frame"].to_numpy(np.int64),
            patches,
            origins,
            group["photons"].to_numpy(np.float64),
        )
    return expected


def expose(
    expected: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    *,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Camera readout of an expected image in photoelectrons: flatfield, Poisson shot noise,
    Gaussian read noise (``camera.readnoise`` e⁻), ``/ gain + offset``, rounding, and clipping to
    0…65,535. Returns uint16 ADU of the same shape."""
    out = np.empty(expected.shape, dtype=np.uint16)
    flat = camera.flatfield_region(expected.shape[-2:], origin=origin)
    planes = expected.reshape(-1, *expected.shape[-2:])
    for k, plane in enumerate(planes):
        mean = plane if flat is None else plane * flat
        electrons = rng.poisson(mean).astype(np.float64)
        if camera.readnoise > 0:
            electrons += rng.normal(0.0, camera.readnoise, size=mean.shape)
        adu = np.rint(camera.to_adu(electrons))
        out.reshape(planes.shape)[k] = np.clip(adu, 0, ADU_MAX)
    return out


def best_focus_defocus_nm(
    optics: Optics,
    aberrations: AberrationMap,
    field_x: np.ndarray,
    field_y: np.ndarray,
    *,
    diameter_nm: Any,
) -> np.ndarray:
    """Defocus (nm) at which the noise-free image amplitude peaks, at each field position.

    ``diameter_nm`` is the emitter diameter (0 for a point), one value or one per position.

    The amplitude is the peak pixel of the pixel-integrated image of an emitter centred on a
    pixel. It is scanned on a 200 nm grid over ±1.6 µm around the field-curvature prediction
    (``Optics.focus_shift_per_defocus_nm`` × Z4), then on a 40 nm grid around the maximum, and
    the maximum is refined by a parabola through the three highest samples (within 1 nm of a
    4 nm scan for the default optics).
    """
    fx = np.atleast_1d(np.asarray(field_x, dtype=np.float64))
    fy = np.atleast_1d(np.asarray(field_y, dtype=np.float64))
    diameters = np.broadcast_to(np.asarray(diameter_nm, dtype=np.float64), fx.shape)
    coef = aberrations.at(fx, fy).reshape(fx.size, len(aberrations.modes))
    basis = optics.zernike_basis(aberrations.modes)
    z4 = coef[:, aberrations.modes.index(4)] if 4 in aberrations.modes else np.zeros(fx.size)
    guess = optics.focus_shift_per_defocus_nm() * z4
    coarse = np.arange(-1600.0, 1600.1, 200.0)
    fine = np.arange(-200.0, 200.1, 40.0)
    out = np.empty(fx.size)
    for i in range(fx.size):
        wave = np.tensordot(coef[i], basis, axes=1)[None]
        diameter = float(diameters[i])
        size = patch_size_px(optics, abs(guess[i]) + 1800.0, diameter)
        centre = float(size // 2)

        def peaks(defocus: np.ndarray, wave=wave, size=size, centre=centre, d=diameter):
            centers = np.full((defocus.size, 2), centre)
            images = optics.render_batch(wave, defocus, centers, (size, size), d)
            return images.max(axis=(1, 2))

        grid = guess[i] + coarse
        best = grid[np.argmax(peaks(grid))]
        grid = best + fine
        values = peaks(grid)
        k = int(np.clip(np.argmax(values), 1, grid.size - 2))
        lo, mid, hi = values[k - 1 : k + 2]
        curvature = lo - 2 * mid + hi
        step = 0.5 * (lo - hi) / curvature if curvature < 0 else 0.0
        out[i] = grid[k] + np.clip(step, -1.0, 1.0) * (fine[1] - fine[0])
    return out


def best_focus_interpolator(
    optics: Optics,
    aberrations: AberrationMap,
    *,
    diameter_nm: float,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    n: int = 9,
):
    """``f(field_x, field_y) -> focus defocus (nm)``: :func:`best_focus_defocus_nm` on an n × n
    grid over the given field ranges, interpolated by bicubic splines (the aberrations are cubic
    in field position, so the interpolation error is far below the 10 nm scan step)."""
    from scipy.interpolate import RectBivariateSpline

    xs = np.linspace(*x_range, n)
    ys = np.linspace(*y_range, n)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    values = best_focus_defocus_nm(
        optics, aberrations, gx.ravel(), gy.ravel(), diameter_nm=diameter_nm
    ).reshape(n, n)
    spline = RectBivariateSpline(xs, ys, values, kx=3, ky=3)
    return lambda fx, fy: spline(np.asarray(fx), np.asarray(fy), grid=False)

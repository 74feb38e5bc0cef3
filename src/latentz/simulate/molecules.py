"""Single-molecule frames: point emitters at random positions and depths, with truth.

An astigmatic 3D-SMLM microscope (:func:`random_microscope`: oil objective, astigmatism along a
random axis) has the same aberrations across its small field, so every molecule's image is one
batch of the pupil-function PSF (:meth:`Optics.render_batch`), fast enough for thousands of
molecules per frame set. The truth of each molecule is where the simulation put it: ``x, y``
(pixels) and ``z_nm``, its height above the focal plane of a point emitter, whose best focus
(the peak of the noise-free image's brightest pixel) is found once for the whole field.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pandas as pd

from latentz._shared.validate import check_positive, check_shape2
from latentz.camera import Camera
from latentz.simulate._render import (
    add_patches,
    best_focus_defocus_nm,
    expose,
    patch_size_px,
    render_patches,
)
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.optics import Optics

__all__ = [
    "Microscope",
    "random_microscope",
    "place_molecules",
    "place_edge_molecules",
    "molecule_frames",
    "molecule_patches",
]

_BATCH = 512  # molecules rendered per batch (memory: batch × patch² × complex pupil)


class Microscope(NamedTuple):
    """Optics, field-constant aberrations and camera of one simulated SMLM microscope."""

    optics: Optics
    aberrations: AberrationMap
    camera: Camera


def random_microscope(
    rng: np.random.Generator,
    *,
    astigmatism_nm: tuple[float, float] = (50.0, 90.0),
    field_shape: tuple[int, int] = (128, 128),
) -> Microscope:
    """A random astigmatic microscope: NA 1.35–1.49 oil objective, emission 580–700 nm, pixels
    95–130 nm, astigmatism of ``astigmatism_nm`` RMS (uniform) along a uniform random axis,
    spherical aberration within ±20 nm and coma within ±10 nm RMS, and an sCMOS-like camera
    (gain 0.4–0.6 e⁻/ADU, read noise 1–2 e⁻)."""
    pixel_nm = rng.uniform(95.0, 130.0)
    optics = Optics(
        na=rng.uniform(1.35, 1.49),
        immersion_index=1.515,
        wavelength_nm=rng.uniform(580.0, 700.0),
        magnification=6500.0 / pixel_nm,
        camera_pixel_um=6.5,
    )
    amount, axis = rng.uniform(*astigmatism_nm), rng.uniform(0.0, np.pi)
    aberrations = AberrationMap.constant(
        {
            5: amount * np.cos(2 * axis),
            6: amount * np.sin(2 * axis),
            7: rng.uniform(-10.0, 10.0),
            8: rng.uniform(-10.0, 10.0),
            11: rng.uniform(-20.0, 20.0),
        },
        field_shape=field_shape,
    )
    camera = Camera(
        offset=100.0,
        gain=rng.uniform(0.4, 0.6),
        readnoise=rng.uniform(1.0, 2.0),
        pixel_size_nm=optics.pixel_size_nm,
    )
    return Microscope(optics, aberrations, camera)


def place_molecules(
    rng: np.random.Generator,
    *,
    n_frames: int,
    frame_shape: tuple[int, int],
    pixel_nm: float,
    density_per_um2: float,
    photons: tuple[float, float] = (300.0, 1e4),
    z_range_nm: tuple[float, float] = (-600.0, 600.0),
) -> pd.DataFrame:
    """Molecules uniform over each frame (pixel centres span −0.5…W−0.5), Poisson
    ``density_per_um2`` per frame, log-uniform ``photons`` and uniform ``z_range_nm``: columns
    ``frame, x, y`` (pixels), ``z_nm``, ``photons``."""
    rows, cols = check_shape2("frame_shape", frame_shape)
    area_um2 = rows * cols * (pixel_nm / 1000.0) ** 2
    counts = rng.poisson(check_positive("density_per_um2", density_per_um2) * area_um2, n_frames)
    n = int(counts.sum())
    return pd.DataFrame(
        {
            "frame": np.repeat(np.arange(n_frames), counts),
            "x": rng.uniform(-0.5, cols - 0.5, n),
            "y": rng.uniform(-0.5, rows - 0.5, n),
            "z_nm": rng.uniform(*z_range_nm, n),
            "photons": np.exp(rng.uniform(*np.log(photons), n)),
        }
    )


def place_edge_molecules(
    rng: np.random.Generator,
    *,
    n_frames: int,
    frame_shape: tuple[int, int],
    depth_px: float = 7.5,
    photons: tuple[float, float] = (3e3, 1e4),
    z_range_nm: tuple[float, float] = (-400.0, 400.0),
) -> pd.DataFrame:
    """Per frame, three molecules along each edge of the frame, 0–``depth_px`` from it, at a
    quarter, half and three quarters of its length (±2 px), and four inside (at 35 and 65 % of
    each side, ±1 px); log-uniform ``photons``, uniform ``z_range_nm``. Columns as
    `place_molecules`, with ``distance_px`` (from the centre of the frame's outermost pixel;
    the inner ones' from the frame's edge) and ``across`` (0: the nearest edge cuts x, 1: y,
    −1: inside)."""
    rows, cols = check_shape2("frame_shape", frame_shape)
    depth_px = check_positive("depth_px", depth_px)
    tables = []
    for frame in range(n_frames):
        along = np.tile([0.25, 0.5, 0.75], 4) + rng.uniform(-2.0, 2.0, 12) / min(rows, cols)
        depth = rng.uniform(0.0, depth_px, 12)
        side = np.repeat(np.arange(4), 3)  # left, right, top, bottom
        x = np.choose(side, [depth, cols - 1 - depth, along * (cols - 1), along * (cols - 1)])
        y = np.choose(side, [along * (rows - 1), along * (rows - 1), depth, rows - 1 - depth])
        inner = np.array([0.35, 0.35, 0.65, 0.65]), np.array([0.35, 0.65, 0.35, 0.65])
        x = np.r_[x, inner[0] * (cols - 1) + rng.uniform(-1.0, 1.0, 4)]
        y = np.r_[y, inner[1] * (rows - 1) + rng.uniform(-1.0, 1.0, 4)]
        tables.append(
            pd.DataFrame(
                {
                    "frame": frame,
                    "x": x,
                    "y": y,
                    "z_nm": rng.uniform(*z_range_nm, 16),
                    "photons": np.exp(rng.uniform(*np.log(photons), 16)),
                    "distance_px": np.minimum.reduce([x, y, cols - 1 - x, rows - 1 - y]),
                    "across": np.r_[np.where(side < 2, 0, 1), np.full(4, -1)],
                }
            )
        )
    return pd.concat(tables, ignore_index=True)


def molecule_patches(
    microscope: Microscope, x: np.ndarray, y: np.ndarray, z_nm: np.ndarray, *,
    size: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Noise-free images (fraction of photons per pixel, (n, size, size)) of point molecules at
    (x, y) (frame px) and ``z_nm`` (height above a point emitter's best focus, nm), and their
    origins ((n, 2) row, column in the frame): what :func:`molecule_frames` adds to its frames.
    ``size`` (px) by default holds the most defocused of them."""
    optics, aberrations, _ = microscope
    coef = aberrations.at(np.array([0.0, 1e6]), np.array([0.0, 1e6]))
    if not np.allclose(coef[0], coef[1]):
        raise ValueError(
            "Expected aberrations that are the same across the field (AberrationMap.constant)."
        )
    focus = float(best_focus_defocus_nm(optics, aberrations, [0.0], [0.0], diameter_nm=0.0)[0])
    x, y, z = (np.asarray(v, np.float64) for v in (x, y, z_nm))
    if size is None:
        size = patch_size_px(optics, float(np.max(np.abs(z), initial=0.0)) + abs(focus), 0.0)
    parts = [render_patches(
        optics, aberrations, x=x[part], y=y[part], field_x=x[part], field_y=y[part],
        defocus_nm=z[part] + focus, diameter_nm=0.0, size=size,
    ) for part in (slice(k, k + _BATCH) for k in range(0, len(z), _BATCH))]  # fmt: skip
    if not parts:
        return np.empty((0, size, size)), np.empty((0, 2), np.int64)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def molecule_frames(
    molecules: pd.DataFrame,
    microscope: Microscope,
    *,
    n_frames: int,
    frame_shape: tuple[int, int],
    background: float = 20.0,
    seed: int = 0,
) -> tuple[np.ndarray, pd.DataFrame]:
    """Camera frames (uint16 ADU) of point ``molecules`` (``frame, x, y, z_nm, photons``; z is the
    height above a point emitter's best focus, nm) over ``background`` photoelectrons per pixel,
    and the truth: ``molecules`` with ``x_nm, y_nm`` (pixel ``[i, j]`` centred at ``x = j``)."""
    optics, _, camera = microscope
    patches, origins = molecule_patches(
        microscope, molecules["x"], molecules["y"], molecules["z_nm"]
    )
    expected = np.full((int(n_frames), *frame_shape), float(background))
    add_patches(expected, molecules["frame"].to_numpy(np.int64), patches, origins,
                molecules["photons"].to_numpy(np.float64))  # fmt: skip
    frames = expose(expected, camera, np.random.default_rng(seed))
    truth = molecules.reset_index(drop=True).copy()
    truth["x_nm"] = truth["x"] * optics.pixel_size_nm
    truth["y_nm"] = truth["y"] * optics.pixel_size_nm
    return frames, truth

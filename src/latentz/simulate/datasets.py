"""Simulated datasets with ground truth: calibration stacks, test spots and aperture arrays.

Axial convention. ``z_nm`` of an emitter is its height in the sample, relative to the nominal
focal plane (the focal plane at the field centre when the piezo is at 0, without aberrations). The
piezo displaces the sample along +z relative to the objective, so in a plane taken at piezo
position ``z_piezo`` the emitter's defocus is ``defocus_nm = z_nm + z_piezo``. With aberrations,
the image's brightest pixel peaks at ``defocus_nm = focus_defocus_nm(x, y)`` (field curvature and
spherical aberration), so a calibration particle is in best focus at the piezo position
``z_focus_nm = focus_defocus_nm − z_nm``, and an emitter's height above the local focal surface is
``z_from_focus_nm = defocus_nm − focus_defocus_nm``.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.validate import (
    check_array,
    check_columns,
    check_finite,
    check_int,
    check_positive,
    check_shape2,
)
from latentz.camera import Camera
from latentz.simulate._render import best_focus_defocus_nm, expose, render_expected
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.files import dataset_metadata, write_files
from latentz.simulate.optics import Optics

__all__ = [
    "CalibrationDataset",
    "ApertureArrayDataset",
    "calibration_dataset",
    "render_spots",
    "aperture_array",
    "stage_origins",
]

DEFECT_KINDS = ("none", "dimer", "large")


def _default_camera(optics: Optics) -> Camera:
    return Camera(pixel_size_nm=optics.pixel_size_nm)


def stage_origins(
    n_stage_positions: int, frame_shape: tuple[int, int], field_shape: tuple[int, int]
) -> np.ndarray:
    """Field origins (row, column) of the frames at ``n`` stage positions, on a grid spread
    evenly over the field so that together they cover it (tiling it when they fit exactly)."""
    n = check_int("n_stage_positions", n_stage_positions, minimum=1)
    (h, w), (fh, fw) = frame_shape, field_shape
    if h > fh or w > fw:
        raise ValueError(f"Expected `frame_shape` {frame_shape} to fit in the field {field_shape}.")
    n_cols = math.ceil(math.sqrt(n))
    n_rows = math.ceil(n / n_cols)
    rows = np.rint(np.linspace(0, fh - h, n_rows) if n_rows > 1 else [(fh - h) / 2])
    cols = np.rint(np.linspace(0, fw - w, n_cols) if n_cols > 1 else [(fw - w) / 2])
    grid = np.array([(r, c) for r in rows for c in cols], dtype=np.int64)
    return grid[:n]


def _place(
    rng: np.random.Generator, n: int, frame_shape: tuple[int, int], margin: float, spacing: float
) -> np.ndarray:
    """``n`` random (x, y) positions at least ``spacing`` px apart and ``margin`` px from edges."""
    h, w = frame_shape
    if w - 1 - 2 * margin <= 0 or h - 1 - 2 * margin <= 0:
        raise ValueError(f"Frames of shape {frame_shape} are too small for margins of {margin} px.")
    points: list[np.ndarray] = []
    for _ in range(200 * n + 100):
        if len(points) == n:
            break
        p = rng.uniform([margin, margin], [w - 1 - margin, h - 1 - margin])
        if all(np.hypot(*(p - q)) >= spacing for q in points):
            points.append(p)
    if len(points) < n:
        raise ValueError(
            f"Cannot place {n} particles {spacing:.0f} px apart in frames of shape {frame_shape}: "
            "use fewer particles, more stage positions or larger frames."
        )
    return np.array(points).reshape(n, 2)


@dataclass(frozen=True, eq=False)
class CalibrationDataset:
    """Through-focus stacks of calibration particles at several stage positions, with truth.

    Attributes
    ----------
    stacks : tuple of ndarray (n_z, H, W) uint16
        One camera stack per stage position, in ADU.
    z_nm : ndarray (n_z,)
        Piezo position of each plane, shared by all stacks.
    origins : ndarray (n_stacks, 2) int
        Field position (row, column) of pixel [0, 0] of each stack: field x = x + column.
    truth : DataFrame
        One row per particle: ``particle, stack, x, y`` (stack pixels), ``field_x, field_y``
        (full-field pixels), ``z_surface_nm`` (substrate under the particle), ``z_nm`` (particle
        centre), ``focus_defocus_nm``, ``z_focus_nm`` (piezo position of best focus: the peak
        of the noise-free image's brightest pixel; the paper's z_f, the peak of the fitted
        Gaussian amplitude, differs from it with spherical aberration: docs/method.md),
        ``diameter_nm``, ``photons``, ``defect`` ('none', 'dimer', 'large') and ``defective``.
    """

    stacks: tuple[np.ndarray, ...]
    z_nm: np.ndarray
    origins: np.ndarray
    truth: pd.DataFrame
    camera: Camera
    optics: Optics
    aberrations: AberrationMap
    tilt_mrad: float
    tilt_direction_rad: float
    background: float
    photons: float
    particle_diameter_nm: float
    seed: int
    field_shape: tuple[int, int] = field(default=(2048, 2048))

    def metadata(self) -> dict[str, Any]:
        """Everything needed to reproduce or interpret the dataset, JSON-ready."""
        meta = dataset_metadata(self)
        meta.update(
            kind="calibration",
            z_nm=self.z_nm.tolist(),
            origins_row_col=self.origins.tolist(),
            field_shape=list(self.field_shape),
            tilt_mrad=self.tilt_mrad,
            tilt_direction_rad=self.tilt_direction_rad,
            tilt_plane="z_surface_nm = -d/2 + tan(tilt) * pixel_nm * "
            "((field_x - (W-1)/2) cos(direction) + (field_y - (H-1)/2) sin(direction))",
            background=self.background,
            photons=self.photons,
            particle_diameter_nm=self.particle_diameter_nm,
        )
        return meta

    def write(self, out_dir: str | os.PathLike) -> list[Path]:
        """Write the dataset to ``out_dir`` (see :func:`latentz.simulate.write_files`)."""
        return write_files(self, out_dir)


def calibration_dataset(
    *,
    n_particles: int = 300,
    z_nm: Any = None,
    n_stage_positions: int = 16,
    tilt_mrad: float = 2.0,
    tilt_direction_rad: float = math.pi / 6,
    particle_diameter_nm: float = 1000.0,
    diameter_sd_nm: float = 24.0,
    photons: float = 5e5,
    background: float = 100.0,
    camera: Camera | None = None,
    optics: Optics | None = None,
    aberrations: AberrationMap | None = None,
    defective_fraction: float = 0.0,
    frame_shape: tuple[int, int] = (512, 512),
    min_spacing_px: float = 50.0,
    seed: int = 0,
) -> CalibrationDataset:
    """Simulate calibration particles on a tilted substrate imaged through focus.

    Random particles lie on a plane tilted by ``tilt_mrad`` (rising along the azimuth
    ``tilt_direction_rad``, measured from +x towards +y) relative to the focal plane; the stage
    moves parallel to that plane. At each of ``n_stage_positions`` the camera records a stack of
    ``frame_shape`` at a different place of the field (``stage_origins``), through the piezo
    positions ``z_nm`` (default 81 planes from −3 to +3 µm).

    Parameters
    ----------
    n_particles : int
        Total particles, split evenly among the stage positions.
    particle_diameter_nm, diameter_sd_nm : float
        Mean and standard deviation of the particle diameters (the paper's: 1000 and 24 nm).
        Photons scale with the particle volume.
    photons : float
        Mean signal photoelectrons per particle and frame (the paper's: about 5e5).
    background : float
        Background photoelectrons per pixel and frame.
    defective_fraction : float
        Fraction (0–1) of particles that are defective: half dimers (two touching particles),
        half particles of twice the diameter (4x the photons); flagged in ``truth``.
    min_spacing_px : float
        Minimum distance between particles, so that their defocused images rarely overlap.
    seed : int
        Seed of all random draws (positions, diameters, defects and noise).

    Returns
    -------
    CalibrationDataset
    """
    optics = optics or Optics()
    aberrations = aberrations or AberrationMap.default(seed=seed)
    camera = camera or _default_camera(optics)
    n_particles = check_int("n_particles", n_particles, minimum=1)
    z = np.linspace(-3000.0, 3000.0, 81) if z_nm is None else z_nm
    z = check_array("z_nm", z, ndim=1, dtype_kind="uif").astype(np.float64)
    if not np.all(np.isfinite(z)):
        raise ValueError("Expected `z_nm` to be finite.")
    tilt = check_positive("tilt_mrad", tilt_mrad, allow_zero=True)
    direction = check_finite("tilt_direction_rad", tilt_direction_rad)
    diameter = check_positive("particle_diameter_nm", particle_diameter_nm)
    diameter_sd = check_positive("diameter_sd_nm", diameter_sd_nm, allow_zero=True)
    photons = check_positive("photons", photons)
    background = check_positive("background", background, allow_zero=True)
    fraction = check_positive("defective_fraction", defective_fraction, allow_zero=True)
    if fraction > 1:
        raise ValueError(f"Expected `defective_fraction` to be <= 1, got {defective_fraction}.")
    frame_shape = check_shape2("frame_shape", frame_shape)
    field_shape = aberrations.field_shape
    origins = stage_origins(n_stage_positions, frame_shape, field_shape)
    rng = np.random.default_rng(seed)

    margin = max(8.0, diameter / optics.pixel_size_nm)
    place = _placements(rng, n_particles, origins, frame_shape, margin, min_spacing_px)
    sizes = _particle_sizes(rng, n_particles, diameter, diameter_sd, fraction, photons)
    diameters, signal = sizes["diameter_nm"].to_numpy(), sizes["photons"].to_numpy()
    xy, stack = place[["x", "y"]].to_numpy(), place["stack"].to_numpy()
    slope = math.tan(tilt * 1e-3) * optics.pixel_size_nm
    heights = _heights(place, diameters, diameter, (slope, direction), optics, aberrations)
    z_centre = heights["z_nm"].to_numpy()
    defect = sizes["defect"].to_numpy(dtype=object)
    lobes = _lobes(xy, diameters, defect, rng.uniform(0, np.pi, n_particles), optics)
    emitters = _through_focus(lobes, z, z_centre, signal, diameters, stack)
    render = functools.partial(
        _stack,
        n_z=z.size,
        frame_shape=frame_shape,
        optics=optics,
        aberrations=aberrations,
        background=background,
        camera=camera,
        rng=rng,
    )
    stacks = [render(emitters[emitters["stack"] == k], o) for k, o in enumerate(origins)]
    truth = pd.concat([place, heights, sizes], axis=1)
    return CalibrationDataset(
        stacks=tuple(stacks),
        z_nm=z,
        origins=origins,
        truth=truth,
        camera=camera,
        optics=optics,
        aberrations=aberrations,
        tilt_mrad=tilt,
        tilt_direction_rad=direction,
        background=background,
        photons=photons,
        particle_diameter_nm=diameter,
        seed=seed,
        field_shape=field_shape,
    )


def _placements(
    rng: np.random.Generator,
    n: int,
    origins: np.ndarray,
    frame_shape: tuple[int, int],
    margin: float,
    spacing: float,
) -> pd.DataFrame:
    """``n`` particles split evenly among the stacks at field ``origins`` (row, column):
    ``particle, stack``, ``x, y`` (stack pixels, :func:`_place`) and ``field_x, field_y``."""
    counts = [len(a) for a in np.array_split(np.arange(n), len(origins))]
    xy = np.concatenate([_place(rng, c, frame_shape, margin, spacing) for c in counts if c > 0])
    stack = np.repeat(np.arange(len(origins)), counts)
    return pd.DataFrame(
        {
            "particle": np.arange(n),
            "stack": stack,
            "x": xy[:, 0],
            "y": xy[:, 1],
            "field_x": xy[:, 0] + origins[stack, 1],
            "field_y": xy[:, 1] + origins[stack, 0],
        }
    )


def _particle_sizes(
    rng: np.random.Generator,
    n: int,
    diameter: float,
    diameter_sd: float,
    fraction: float,
    photons: float,
) -> pd.DataFrame:
    """``diameter_nm``, signal ``photons`` (photoelectrons per frame), ``defect`` and
    ``defective`` of ``n`` random particles, a ``fraction`` of them defective (half dimers,
    half twice as large)."""
    diameters = np.clip(rng.normal(diameter, diameter_sd, n), 0.5 * diameter, None)
    n_bad = int(round(fraction * n))
    defect = np.full(n, "none", dtype=object)
    bad = rng.choice(n, size=n_bad, replace=False)
    defect[bad[: (n_bad + 1) // 2]] = "dimer"
    defect[bad[(n_bad + 1) // 2 :]] = "large"
    diameters = np.where(defect == "large", 2 * diameters, diameters)
    signal = photons * (diameters / diameter) ** 3
    signal = np.where(defect == "large", signal / 2.0, signal)  # surface-limited dye loading
    return pd.DataFrame(
        {
            "diameter_nm": diameters,
            "photons": signal,
            "defect": pd.Categorical(defect, categories=DEFECT_KINDS),
            "defective": defect != "none",
        }
    )


def _heights(
    place: pd.DataFrame,
    diameters: np.ndarray,
    diameter: float,
    tilt: tuple[float, float],
    optics: Optics,
    aberrations: AberrationMap,
) -> pd.DataFrame:
    """Per particle (nm): the substrate under it, on a plane through the field centre rising
    by ``tilt[0]`` nm per pixel along the azimuth ``tilt[1]`` (rad, from +x towards +y) and
    touching the bottom of a particle of the mean ``diameter``; its centre; the defocus of its
    best focus and the piezo position of it."""
    rows, cols = aberrations.field_shape
    slope, direction = tilt
    field_x, field_y = place["field_x"].to_numpy(), place["field_y"].to_numpy()
    z_surface = -diameter / 2 + slope * (
        (field_x - (cols - 1) / 2) * math.cos(direction)
        + (field_y - (rows - 1) / 2) * math.sin(direction)
    )
    z_centre = z_surface + diameters / 2
    # Best focus of each particle (a dimer's lobes are in the same plane as a single particle).
    focus = best_focus_defocus_nm(optics, aberrations, field_x, field_y, diameter_nm=diameters)
    return pd.DataFrame(
        {
            "z_surface_nm": z_surface,
            "z_nm": z_centre,
            "focus_defocus_nm": focus,
            "z_focus_nm": focus - z_centre,
        }
    )


def _lobes(
    xy: np.ndarray, diameters: np.ndarray, defect: np.ndarray, angle: np.ndarray, optics: Optics
) -> pd.DataFrame:
    """One emitter per particle (``particle, x, y, emitter``, pixels), two for a dimer: its
    touching halves, along ``angle`` (rad)."""
    lobes = []
    for i in range(len(xy)):
        if defect[i] == "dimer":
            dx = 0.5 * diameters[i] / optics.pixel_size_nm * math.cos(angle[i])
            dy = 0.5 * diameters[i] / optics.pixel_size_nm * math.sin(angle[i])
            lobes += [(i, xy[i, 0] + dx, xy[i, 1] + dy), (i, xy[i, 0] - dx, xy[i, 1] - dy)]
        else:
            lobes.append((i, xy[i, 0], xy[i, 1]))
    lobe_table = pd.DataFrame(lobes, columns=["particle", "x", "y"])
    lobe_table["emitter"] = np.arange(len(lobe_table))
    return lobe_table


def _through_focus(
    lobes: pd.DataFrame,
    z: np.ndarray,
    z_centre: np.ndarray,
    signal: np.ndarray,
    diameters: np.ndarray,
    stack: np.ndarray,
) -> pd.DataFrame:
    """Every lobe in every plane: its frame, defocus (nm), photons, diameter and stack."""
    n_z = z.size
    emitters = lobes.loc[lobes.index.repeat(n_z)].reset_index(drop=True)
    emitters["frame"] = np.tile(np.arange(n_z), len(lobes))
    p = emitters["particle"].to_numpy()
    emitters["defocus_nm"] = z_centre[p] + z[emitters["frame"].to_numpy()]
    emitters["photons"] = signal[p]
    emitters["diameter_nm"] = diameters[p]
    emitters["stack"] = stack[p]
    return emitters


def _stack(
    emitters: pd.DataFrame,
    origin: np.ndarray,
    *,
    n_z: int,
    frame_shape: tuple[int, int],
    optics: Optics,
    aberrations: AberrationMap,
    background: float,
    camera: Camera,
    rng: np.random.Generator,
) -> np.ndarray:
    """The camera stack (ADU) of ``emitters`` in frames at field ``origin`` (row, column)."""
    at = (int(origin[0]), int(origin[1]))
    expected = render_expected(
        emitters,
        n_frames=n_z,
        frame_shape=frame_shape,
        origin=at,
        optics=optics,
        aberrations=aberrations,
        background=background,
    )
    return expose(expected, camera, rng, origin=at)


def _frame_values(name: str, value: Any, n_frames: int) -> np.ndarray:
    arr = check_array(name, value, ndim=(0, 1), dtype_kind="uif").astype(np.float64)
    arr = np.broadcast_to(arr, (n_frames,)) if arr.ndim == 0 else arr
    if arr.shape != (n_frames,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"Expected `{name}` to be one finite value or one per frame ({n_frames}).")
    return arr


def render_spots(
    spots: pd.DataFrame,
    *,
    frame_shape: tuple[int, int] = (64, 64),
    n_frames: int | None = None,
    origin: tuple[int, int] = (0, 0),
    z_piezo_nm: Any = 0.0,
    photons: float = 5e5,
    diameter_nm: float = 1000.0,
    background: float = 100.0,
    camera: Camera | None = None,
    optics: Optics | None = None,
    aberrations: AberrationMap | None = None,
    noise: bool = True,
    seed: int = 0,
) -> tuple[np.ndarray, pd.DataFrame]:
    """Render test emitters at given positions and heights, for accuracy tests.

    Parameters
    ----------
    spots : DataFrame
        One row per emitter instance. Required: ``x, y`` (frame pixels) and ``z_nm`` (height,
        see the module notes). Optional: ``frame`` (default 0), ``photons`` and ``diameter_nm``
        (default the keyword values; 0 is a point emitter).
    frame_shape : (rows, columns)
        Frame size in pixels.
    n_frames : int, optional
        Number of frames; default ``max(frame) + 1``.
    origin : (row, column)
        Field position of pixel [0, 0], for the aberrations (the field is
        ``aberrations.field_shape``).
    z_piezo_nm : float or array (n_frames,)
        Piezo position of each frame.
    noise : bool
        True: camera frames (uint16 ADU). False: the expected image in photoelectrons (float64,
        background included, no flatfield), for noise-free tests.

    Returns
    -------
    frames : ndarray (n_frames, rows, columns)
    truth : DataFrame
        ``spots`` with ``frame, photons, diameter_nm`` filled in and ``field_x, field_y``,
        ``defocus_nm``, ``focus_defocus_nm`` and ``z_from_focus_nm`` added.
    """
    optics = optics or Optics()
    aberrations = aberrations or AberrationMap.default(seed=0)
    camera = camera or _default_camera(optics)
    check_columns("spots", spots, ("x", "y", "z_nm"))
    frame_shape = check_shape2("frame_shape", frame_shape)
    truth = spots.copy().reset_index(drop=True)
    for name, default in (("frame", 0), ("photons", photons), ("diameter_nm", diameter_nm)):
        if name not in truth.columns:
            truth[name] = default
    for name in ("x", "y", "z_nm", "photons", "diameter_nm"):
        values = check_array(name, truth[name].to_numpy(), ndim=1, dtype_kind="uif")
        if not np.all(np.isfinite(values)):
            raise ValueError(f"Expected `spots[{name!r}]` to be finite.")
    if np.any(truth["photons"] < 0) or np.any(truth["diameter_nm"] < 0):
        raise ValueError("Expected `spots` photons and diameter_nm to be >= 0.")
    frames_index = truth["frame"].to_numpy()
    if frames_index.dtype.kind not in "iu" or np.any(frames_index < 0):
        raise ValueError("Expected `spots['frame']` to hold non-negative integers.")
    n = (
        int(frames_index.max()) + 1
        if n_frames is None
        else check_int("n_frames", n_frames, minimum=1)
    )
    if frames_index.max() >= n:
        raise ValueError(f"`spots` refers to frame {frames_index.max()} but n_frames is {n}.")
    piezo = _frame_values("z_piezo_nm", z_piezo_nm, n)
    background = check_positive("background", background, allow_zero=True)
    r0, c0 = (check_int("origin", int(v), minimum=0) for v in origin)

    truth["field_x"] = truth["x"] + c0
    truth["field_y"] = truth["y"] + r0
    truth["defocus_nm"] = truth["z_nm"] + piezo[frames_index]
    truth["focus_defocus_nm"] = best_focus_defocus_nm(
        optics,
        aberrations,
        truth["field_x"].to_numpy(),
        truth["field_y"].to_numpy(),
        diameter_nm=truth["diameter_nm"].to_numpy(np.float64),
    )
    truth["z_from_focus_nm"] = truth["defocus_nm"] - truth["focus_defocus_nm"]
    emitters = truth[["frame", "x", "y", "defocus_nm", "photons", "diameter_nm"]].copy()
    emitters["emitter"] = np.arange(len(emitters))
    expected = render_expected(
        emitters,
        n_frames=n,
        frame_shape=frame_shape,
        origin=(r0, c0),
        optics=optics,
        aberrations=aberrations,
        background=background,
    )
    if not noise:
        return expected, truth
    return expose(expected, camera, np.random.default_rng(seed), origin=(r0, c0)), truth


@dataclass(frozen=True, eq=False)
class ApertureArrayDataset:
    """Frames of a regular array of sub-resolution apertures, with truth.

    Attributes
    ----------
    frames : ndarray (n_frames, H, W) uint16
        Camera frames in ADU, one per entry of ``z_nm``.
    z_nm : ndarray (n_frames,)
        Piezo position of each frame.
    truth : DataFrame
        One row per aperture: ``aperture, row, column`` (array indices), ``x_nm, y_nm`` (sample
        position relative to the array centre), ``x, y`` (true image position in frame pixels,
        after rotation, true pixel size and distortion), ``field_x, field_y``.
    pitch_nm, pixel_size_nm, rotation_rad, distortion :
        The true pitch, the true sample-plane pixel size, the array's rotation relative to the
        camera axes, and the radial distortion coefficient (0: none).
    """

    frames: np.ndarray
    z_nm: np.ndarray
    truth: pd.DataFrame
    pitch_nm: float
    pixel_size_nm: float
    rotation_rad: float
    distortion: float
    origin: tuple[int, int]
    camera: Camera
    optics: Optics
    aberrations: AberrationMap
    seed: int

    def metadata(self) -> dict[str, Any]:
        """Everything needed to reproduce or interpret the dataset, JSON-ready."""
        meta = dataset_metadata(self)
        meta.update(
            kind="apertures",
            z_nm=self.z_nm.tolist(),
            pitch_nm=self.pitch_nm,
            pixel_size_nm_true=self.pixel_size_nm,
            rotation_rad=self.rotation_rad,
            distortion=self.distortion,
            distortion_model="r_image = r (1 + distortion * (r / R)^2), r from the field centre, "
            "R = half the field width",
            origin_row_col=list(self.origin),
        )
        return meta

    def write(self, out_dir: str | os.PathLike) -> list[Path]:
        """Write the dataset to ``out_dir`` (see :func:`latentz.simulate.write_files`)."""
        return write_files(self, out_dir)


def aperture_array(
    *,
    pitch_nm: float = 5000.0,
    shape: tuple[int, int] = (256, 256),
    pixel_size_nm: float = 129.3,
    rotation_rad: float = 0.004,
    distortion: float | None = None,
    origin: tuple[int, int] | None = None,
    z_nm: Any = (0.0, 0.0, 0.0, 0.0),
    photons: float = 2e4,
    background: float = 50.0,
    camera: Camera | None = None,
    optics: Optics | None = None,
    aberrations: AberrationMap | None = None,
    seed: int = 0,
) -> ApertureArrayDataset:
    """Simulate a regular square array of sub-resolution (point-like) apertures.

    The array has pitch ``pitch_nm``, is rotated by ``rotation_rad`` and offset by a random
    sub-pitch amount, and is imaged with the true sample-plane pixel ``pixel_size_nm`` (slightly
    off the nominal 130 nm, as in the paper): the optics' magnification is set to
    ``camera_pixel_um * 1000 / pixel_size_nm``. ``distortion`` adds radial distortion
    ``r (1 + distortion (r/R)²)`` about the field centre. The frames of ``shape`` sit at
    ``origin`` (row, column) in the field, by default its centre. One frame per ``z_nm``.
    """
    base = optics or Optics()
    pixel = check_positive("pixel_size_nm", pixel_size_nm)
    optics = Optics(
        na=base.na,
        wavelength_nm=base.wavelength_nm,
        immersion_index=base.immersion_index,
        magnification=base.camera_pixel_um * 1000.0 / pixel,
        camera_pixel_um=base.camera_pixel_um,
        pupil_samples=base.pupil_samples,
    )
    aberrations = aberrations or AberrationMap.default(seed=seed)
    camera = camera or _default_camera(base)
    pitch = check_positive("pitch_nm", pitch_nm)
    rotation = check_finite("rotation_rad", rotation_rad)
    kappa = 0.0 if distortion is None else check_finite("distortion", distortion)
    shape = check_shape2("shape", shape)
    fh, fw = aberrations.field_shape
    if origin is None:
        origin = ((fh - shape[0]) // 2, (fw - shape[1]) // 2)
    r0, c0 = (check_int("origin", int(v), minimum=0) for v in origin)
    z = check_array("z_nm", np.atleast_1d(np.asarray(z_nm, dtype=float)), ndim=1)
    rng = np.random.default_rng(seed)

    table = _aperture_lattice(rng, pitch, rotation, kappa, pixel, shape, (r0, c0), (fh, fw))
    table.insert(0, "aperture", np.arange(len(table)))
    spots = table.loc[table.index.repeat(z.size), ["x", "y"]].reset_index(drop=True)
    spots["frame"] = np.tile(np.arange(z.size), len(table))
    spots["z_nm"] = 0.0
    frames, _ = render_spots(
        spots,
        frame_shape=shape,
        n_frames=z.size,
        origin=(r0, c0),
        z_piezo_nm=z,
        photons=check_positive("photons", photons),
        diameter_nm=0.0,
        background=background,
        camera=camera,
        optics=optics,
        aberrations=aberrations,
        seed=seed,
    )
    return ApertureArrayDataset(
        frames=frames,
        z_nm=z,
        truth=table,
        pitch_nm=pitch,
        pixel_size_nm=pixel,
        rotation_rad=rotation,
        distortion=kappa,
        origin=(r0, c0),
        camera=camera,
        optics=optics,
        aberrations=aberrations,
        seed=seed,
    )


def _aperture_lattice(
    rng: np.random.Generator,
    pitch: float,
    rotation: float,
    kappa: float,
    pixel: float,
    shape: tuple[int, int],
    origin: tuple[int, int],
    field_shape: tuple[int, int],
) -> pd.DataFrame:
    """The apertures of a square lattice (``pitch`` nm, rotated by ``rotation`` rad, offset by
    a random sub-pitch amount) that image inside frames of ``shape`` at field ``origin``,
    with radial distortion ``kappa``: ``row, column, x_nm, y_nm, x, y, field_x, field_y``."""
    (r0, c0), (fh, fw) = origin, field_shape
    extent_nm = math.hypot(*shape) * pixel
    n_side = int(extent_nm // pitch) + 3
    idx = np.arange(n_side) - n_side // 2
    rows_i, cols_j = (a.ravel() for a in np.meshgrid(idx, idx, indexing="ij"))
    offset = rng.uniform(-0.5, 0.5, 2) * pitch
    x_nm = cols_j * pitch + offset[0]
    y_nm = rows_i * pitch + offset[1]
    cos, sin = math.cos(rotation), math.sin(rotation)
    fx0, fy0 = c0 + (shape[1] - 1) / 2, r0 + (shape[0] - 1) / 2  # array centre in field px
    dx = (cos * x_nm - sin * y_nm) / pixel + fx0 - (fw - 1) / 2
    dy = (sin * x_nm + cos * y_nm) / pixel + fy0 - (fh - 1) / 2
    scale = 1.0 + kappa * (dx**2 + dy**2) / (fw / 2.0) ** 2
    field_x = (fw - 1) / 2 + dx * scale
    field_y = (fh - 1) / 2 + dy * scale
    margin = 6.0
    keep = (
        (field_x - c0 >= margin)
        & (field_x - c0 <= shape[1] - 1 - margin)
        & (field_y - r0 >= margin)
        & (field_y - r0 <= shape[0] - 1 - margin)
    )
    if not np.any(keep):
        raise ValueError(f"No aperture of pitch {pitch} nm falls inside frames of shape {shape}.")
    return pd.DataFrame(
        {
            "row": rows_i[keep] - rows_i[keep].min(),
            "column": cols_j[keep] - cols_j[keep].min(),
            "x_nm": x_nm[keep],
            "y_nm": y_nm[keep],
            "x": field_x[keep] - c0,
            "y": field_y[keep] - r0,
            "field_x": field_x[keep],
            "field_y": field_y[keep],
        }
    )

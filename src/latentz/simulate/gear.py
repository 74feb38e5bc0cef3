"""The paper's microsystem: a load gear carrying fluorescent particles, imaged once per motion
cycle, with the true positions and rigid motion from :mod:`latentz.simulate.gear_motion`."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.validate import check_finite, check_int, check_positive, check_shape2
from latentz.camera import Camera
from latentz.simulate._render import best_focus_interpolator, expose, render_expected
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.files import dataset_metadata, write_files
from latentz.simulate.gear_motion import GearTruth, gear_trajectory
from latentz.simulate.optics import Optics

__all__ = ["GearMovie", "gear_movie"]

_CHUNK_PIXELS = 2**25  # expected-image pixels rendered at once (256 MB of float64)


@dataclass(frozen=True, eq=False)
class GearMovie:
    """A movie of particles on a rotating load gear, one frame per motion cycle, with truth.

    Attributes
    ----------
    frames : ndarray (n_cycles + 1, H, W) uint16
        Camera frames in ADU.
    truth : DataFrame
        One row per particle and frame: ``frame, particle, x_nm, y_nm, z_nm`` (sample
        coordinates from ``gear_trajectory``: gear centre at the origin, z = height relative to
        the nominal focal plane), ``x, y`` (frame pixels), ``field_x, field_y``,
        ``defocus_nm`` (= z_nm + z_piezo_nm), ``focus_defocus_nm``, ``z_from_focus_nm``,
        ``photons``, ``diameter_nm`` and ``in_frame`` (False when the particle lies outside the
        frame or within 4 px of its edge: it is rendered only partly, or not at all).
    motion : DataFrame
        True motion per transition (``GearTruth.motion``): frame, gamma, beta, alpha,
        alpha_defined, dx_nm, dy_nm, dz_nm (about ``gear.centre_nm``).
    gear : GearTruth
        The full kinematic truth (rotations, translations, poses, body coordinates).
    centre_px : (x, y)
        Frame position of the sample origin (the nominal gear centre).
    """

    frames: np.ndarray
    truth: pd.DataFrame
    motion: pd.DataFrame
    gear: GearTruth
    centre_px: tuple[float, float]
    origin: tuple[int, int]
    z_piezo_nm: float
    camera: Camera
    optics: Optics
    aberrations: AberrationMap
    background: float
    photons: float
    particle_diameter_nm: float
    seed: int

    def metadata(self) -> dict[str, Any]:
        """Everything needed to reproduce or interpret the dataset, JSON-ready."""
        meta = dataset_metadata(self)
        meta.update(
            kind="gear",
            n_frames=int(self.frames.shape[0]),
            centre_px=list(self.centre_px),
            origin_row_col=list(self.origin),
            z_piezo_nm=self.z_piezo_nm,
            centre_of_rotation_nm=self.gear.centre_nm.tolist(),
            background=self.background,
            photons=self.photons,
            particle_diameter_nm=self.particle_diameter_nm,
            position_to_pixels="x = centre_px[0] + x_nm / optics.pixel_size_nm, "
            "y = centre_px[1] + y_nm / optics.pixel_size_nm",
        )
        return meta

    def motion_of(self, tracks: pd.DataFrame, *, max_px: float = 3.0) -> pd.DataFrame:
        """The true motion of the transitions that ``tracks`` measure, about the same centre.

        :func:`latentz.motion.rigid_motion` expresses translations about the mean of all tracked
        positions, in the microscope's coordinates (field position × pixel size, calibrated z).
        The same point of the body, in the sample coordinates of the truth, is the mean of the
        *true* positions of the same observations; the truth is expressed about it
        (:meth:`GearTruth.motion_about`), so the two compare directly whichever spots were
        missed. Passing the measured centre itself would mix the two coordinate systems: an
        error of (R − I) times the gear's position in the field, γ × 130 µm in Δx and Δy.

        Each row of ``tracks`` (frame, x, y in this movie's frame pixels; x_nm, y_nm, z_nm) is
        matched to the nearest true particle of its frame within ``max_px``. Rows that match none
        (spurious spots) still pull the measured centre; the same pull, the measured centre minus
        the mean of the matched rows' measured positions, is added to the true centre (the two
        coordinate systems differ by a translation and a scale within 0.1 %).
        """
        from scipy.spatial import cKDTree

        true, matched, measured = [], [], []
        for frame, group in tracks.groupby("frame", sort=False):
            here = self.truth[self.truth["frame"] == frame]
            measured.append(group[["x_nm", "y_nm", "z_nm"]].to_numpy(dtype=float))
            if here.empty:
                matched.append(np.zeros(len(group), dtype=bool))
                true.append(np.full((len(group), 3), np.nan))
                continue
            dist, idx = cKDTree(here[["x", "y"]].to_numpy()).query(group[["x", "y"]].to_numpy())
            matched.append(dist <= max_px)
            true.append(here[["x_nm", "y_nm", "z_nm"]].to_numpy()[idx])
        ok, true, measured = map(np.concatenate, (matched, true, measured))
        if not ok.any():
            raise ValueError(f"No tracked spot lies within {max_px} px of a true particle.")
        pull = measured.mean(axis=0) - measured[ok].mean(axis=0)
        return self.gear.motion_about(true[ok].mean(axis=0) + pull)

    def write(self, out_dir: str | os.PathLike) -> list[Path]:
        """Write the movie, truth, motion and metadata to ``out_dir``."""
        return write_files(self, out_dir)


def gear_movie(
    *,
    n_cycles: int = 64,
    n_particles: int = 28,
    gear_diameter_um: float = 328.0,
    play_nm: float = 400.0,
    nutation_mrad: float = 9.4,
    flexure_period_cycles: float | None = None,
    flexure_amplitude_nm: float = 0.0,
    photons: float = 5e5,
    particle_diameter_nm: float = 1000.0,
    background: float = 100.0,
    frame_shape: tuple[int, int] | None = None,
    origin: tuple[int, int] | None = None,
    z_piezo_nm: float = 0.0,
    camera: Camera | None = None,
    optics: Optics | None = None,
    aberrations: AberrationMap | None = None,
    quick: bool = False,
    seed: int = 0,
    **motion_options: Any,
) -> GearMovie:
    """Simulate the paper's load gear (328 µm, ~28 particles, 1/64 revolution per cycle).

    The true kinematics come from :func:`latentz.simulate.gear_motion.gear_trajectory` (in-plane
    play, out-of-plane rocking and optional flexure; ``motion_options`` pass further keywords to
    it). Positions in nm are mapped to pixels with the optics' true sample pixel, with the gear
    centre at the centre of the frame; the frame (default the whole field, 2048 × 2048) sits at
    ``origin`` (row, column) in the field, default centred.

    ``quick=True`` simulates a small version in a few seconds: 4 cycles, 10 particles on a
    100 µm gear, in a 1024 × 1024 frame.
    """
    optics = optics or Optics()
    aberrations = aberrations or AberrationMap.default(seed=seed)
    camera = camera or Camera(pixel_size_nm=optics.pixel_size_nm)
    if quick:
        n_cycles, n_particles, gear_diameter_um = min(n_cycles, 4), min(n_particles, 10), 100.0
        frame_shape = frame_shape or (1024, 1024)
    fh, fw = aberrations.field_shape
    frame_shape = check_shape2("frame_shape", frame_shape or (fh, fw))
    if origin is None:
        origin = ((fh - frame_shape[0]) // 2, (fw - frame_shape[1]) // 2)
    r0, c0 = (check_int("origin", int(v), minimum=0) for v in origin)
    photons = check_positive("photons", photons)
    diameter = check_positive("particle_diameter_nm", particle_diameter_nm)
    background = check_positive("background", background, allow_zero=True)
    piezo = check_finite("z_piezo_nm", z_piezo_nm)
    gear = gear_trajectory(
        n_cycles,
        n_particles=n_particles,
        gear_diameter_um=gear_diameter_um,
        play_nm=play_nm,
        nutation_mrad=nutation_mrad,
        flexure_period_cycles=flexure_period_cycles,
        flexure_amplitude_nm=flexure_amplitude_nm,
        seed=seed,
        **motion_options,
    )
    truth, centre = _truth(gear, frame_shape, (r0, c0), piezo, optics, aberrations, diameter)
    truth["photons"] = photons
    truth["diameter_nm"] = diameter
    truth["in_frame"] = _in_frame(truth, frame_shape, margin=4.0)
    frames = _render(truth, frame_shape, (r0, c0), optics, aberrations, background, camera, seed)
    return GearMovie(
        frames=frames,
        truth=truth,
        motion=gear.motion,
        gear=gear,
        centre_px=centre,
        origin=(r0, c0),
        z_piezo_nm=piezo,
        camera=camera,
        optics=optics,
        aberrations=aberrations,
        background=background,
        photons=photons,
        particle_diameter_nm=diameter,
        seed=seed,
    )


def _truth(
    gear: GearTruth,
    frame_shape: tuple[int, int],
    origin: tuple[int, int],
    piezo: float,
    optics: Optics,
    aberrations: AberrationMap,
    diameter: float,
) -> tuple[pd.DataFrame, tuple[float, float]]:
    """The gear's particle positions in frame pixels (gear centre at the frame centre) and
    field pixels, with their defocus and height above the local focal surface (nm); and the
    frame centre (x, y) in pixels."""
    height, width = frame_shape
    r0, c0 = origin
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    truth = gear.positions[["frame", "particle", "x_nm", "y_nm", "z_nm"]].copy()
    truth = truth.reset_index(drop=True)
    pixel = optics.pixel_size_nm
    truth["x"] = centre[0] + truth["x_nm"] / pixel
    truth["y"] = centre[1] + truth["y_nm"] / pixel
    truth["field_x"] = truth["x"] + c0
    truth["field_y"] = truth["y"] + r0
    truth["defocus_nm"] = truth["z_nm"] + piezo
    focus = best_focus_interpolator(
        optics,
        aberrations,
        diameter_nm=diameter,
        x_range=(float(truth["field_x"].min()), float(truth["field_x"].max())),
        y_range=(float(truth["field_y"].min()), float(truth["field_y"].max())),
    )
    truth["focus_defocus_nm"] = focus(truth["field_x"], truth["field_y"])
    truth["z_from_focus_nm"] = truth["defocus_nm"] - truth["focus_defocus_nm"]
    return truth, centre


def _in_frame(truth: pd.DataFrame, frame_shape: tuple[int, int], margin: float) -> pd.Series:
    """Whether each particle lies at least ``margin`` pixels inside the frame."""
    height, width = frame_shape
    return (
        (truth["x"] >= margin)
        & (truth["x"] <= width - 1 - margin)
        & (truth["y"] >= margin)
        & (truth["y"] <= height - 1 - margin)
    )


def _render(
    truth: pd.DataFrame,
    frame_shape: tuple[int, int],
    origin: tuple[int, int],
    optics: Optics,
    aberrations: AberrationMap,
    background: float,
    camera: Camera,
    seed: int,
) -> np.ndarray:
    """The camera movie (ADU) of the particles in ``truth``, rendered a bounded number of
    pixels at a time."""
    height, width = frame_shape
    rng = np.random.default_rng(seed)
    n_frames = int(truth["frame"].max()) + 1
    frames = np.empty((n_frames, height, width), dtype=np.uint16)
    chunk = max(1, _CHUNK_PIXELS // (height * width))
    emitters = truth[["frame", "x", "y", "defocus_nm", "photons", "diameter_nm"]].copy()
    emitters["emitter"] = truth["particle"]
    for start in range(0, n_frames, chunk):
        stop = min(start + chunk, n_frames)
        part = emitters[(emitters["frame"] >= start) & (emitters["frame"] < stop)].copy()
        part["frame"] -= start
        expected = render_expected(
            part,
            n_frames=stop - start,
            frame_shape=frame_shape,
            origin=origin,
            optics=optics,
            aberrations=aberrations,
            background=background,
        )
        frames[start:stop] = expose(expected, camera, rng, origin=origin)
    return frames

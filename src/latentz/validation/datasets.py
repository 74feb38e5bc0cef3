"""Calibration stacks and test frames from the validation microscope, with their ground truth.

Calibration: beads on a tilted substrate in through-focus stacks (one piezo z list for every
stack), each stack holding its own particles on a jittered grid. Test: point emitters at other
places in the field (on their own jittered grid, offset from the calibration particles'), each
with its own brightness and its own defocus in every frame. Images are expected photons (the
optics, a uniform background) turned into ADU by Poisson shot noise, Gaussian read noise, a gain
and an offset.

Axial truth is the emitter's defocus from the curved focal surface, ``a``; the calibration's
z = 0 is the calibration beads' surface of best focus after a plane is removed, so the true
calibrated z of a test spot is ``a`` plus the best-focus offset at its place, minus that plane
(:func:`latentz.validation.truth.score`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from latentz.camera import Camera
from latentz.validation.fields import AberrationFields
from latentz.validation.microscope import Microscope, bead_slices

__all__ = ["SIZES", "ValidationData", "emitter_images", "make_data", "render_patches",
           "simulate_study"]  # fmt: skip

#: The study sizes: "full" is the independent validation microscope of docs/validation.md
#: (256 x 256 px, 128 beads), "small" runs in seconds for the tests.
SIZES = {
    "full": {
        "field_px": 256,
        "grid": 8,
        "n_stacks": 2,
        "z_half_nm": 3000.0,
        "z_step_nm": 50.0,
        "photons": 2e5,
        "n_test": 60,
        "n_frames": 10,
        "test_half_nm": 2000.0,
        "patch_px": 31,
    },
    "small": {
        "field_px": 128,
        "grid": 4,
        "n_stacks": 2,
        "z_half_nm": 2000.0,
        "z_step_nm": 100.0,
        "photons": 2e5,
        "n_test": 16,
        "n_frames": 6,
        "test_half_nm": 1500.0,
        "patch_px": 23,
    },
}


@dataclass(frozen=True, eq=False)
class ValidationData:
    """Images and truth of one validation study.

    Attributes
    ----------
    microscope : Microscope
    fields : AberrationFields
    camera : Camera
        The camera that made the ADU (offset, gain, read noise, pixel size).
    stacks : list of ndarray (n_z, H, W)
        Calibration stacks, ADU.
    expected : list of ndarray (n_z, H, W)
        The same stacks without noise, photons (for the truth's best focus).
    z_nm : ndarray (n_z,)
        Piezo position of each calibration plane.
    calibration_truth : DataFrame
        ``particle``, ``stack``, ``x``, ``y`` (field px), ``photons``, ``substrate_nm``.
    frames : ndarray (n_frames, H, W)
        Test frames, ADU.
    test_truth : DataFrame
        One row per test spot: ``emitter``, ``frame``, ``x``, ``y`` (px), ``photons``,
        ``defocus_nm`` (from the focal surface).
    background : float
        Photons per pixel.
    bead_nm : float
        Calibration bead diameter.
    """

    microscope: Microscope
    fields: AberrationFields
    camera: Camera
    stacks: list[np.ndarray]
    expected: list[np.ndarray]
    z_nm: np.ndarray
    calibration_truth: pd.DataFrame
    frames: np.ndarray
    test_truth: pd.DataFrame
    background: float
    bead_nm: float


def _grid(n_side: int, field_px: int, shift: float, jitter: float, rng) -> np.ndarray:
    """(n_side², 2) jittered grid points (x, y) in pixels, at ``shift`` of a cell."""
    cell = field_px / n_side
    i, j = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="xy")
    base = np.column_stack([i.ravel(), j.ravel()]) + shift
    return (base + rng.uniform(-jitter, jitter, base.shape)) * cell


def render_patches(
    microscope: Microscope,
    fields: AberrationFields,
    x_px: float,
    y_px: float,
    defocus_nm: np.ndarray,
    size: int,
    *,
    bead_nm: float = 0.0,
) -> np.ndarray:
    """(m, size, size) expected photon fraction of one emitter at (x, y) for each defocus,
    centred on the pixel nearest the emitter. Every plane fills the whole patch: a patch cut
    to the spot's central disc drops its rings and comatic flare, which pull a fitted centre
    by a different amount at each sub-pixel phase (docs/validation.md)."""
    wave = microscope.wavefront_nm(fields.coefficients([x_px], [y_px])[0])
    offsets, discs, weights = bead_slices(bead_nm)
    dx, dy = x_px - np.rint(x_px), y_px - np.rint(y_px)
    out = np.zeros((len(defocus_nm), size, size))
    for chunk in np.array_split(np.arange(len(defocus_nm)), max(1, len(defocus_nm) // 8)):
        planes = (defocus_nm[chunk][:, None] + offsets[None, :]).ravel()
        img = microscope.pixel_image(dx, dy, wave, planes, size,
                                     disc_radius_nm=np.tile(discs, chunk.size))  # fmt: skip
        out[chunk] = np.einsum("msij,s->mij", img.reshape(chunk.size, offsets.size, size, size),
                               weights)  # fmt: skip
    return out


def _add(frame: np.ndarray, patch: np.ndarray, x_px: float, y_px: float) -> None:
    """Add ``patch`` centred on the pixel nearest (x, y), clipped at the frame's edges."""
    size = patch.shape[-1]
    r0, c0 = int(np.rint(y_px)) - size // 2, int(np.rint(x_px)) - size // 2
    h, w = frame.shape[-2:]
    rs, cs = slice(max(r0, 0), min(r0 + size, h)), slice(max(c0, 0), min(c0 + size, w))
    frame[..., rs, cs] += patch[..., rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]


def emitter_images(
    microscope: Microscope,
    fields: AberrationFields,
    test_truth: pd.DataFrame,
    frame_shape: tuple[int, int],
    background: float,
    patch_px: int,
) -> np.ndarray:
    """(n_frames, H, W) expected photons of the test frames without noise: every emitter of
    ``test_truth`` (rows in frame order per emitter) with its ``photons`` and ``defocus_nm``."""
    n_frames = int(test_truth["frame"].max()) + 1
    expected = np.full((n_frames, *frame_shape), float(background))
    for _, rows in test_truth.groupby("emitter", sort=True):
        x, y = float(rows["x"].iloc[0]), float(rows["y"].iloc[0])
        patch = render_patches(microscope, fields, x, y, rows["defocus_nm"].to_numpy(), patch_px)
        block = np.zeros((n_frames, *patch.shape[1:]))
        block[rows["frame"].to_numpy()] = rows["photons"].to_numpy()[:, None, None] * patch
        _add(expected, block, x, y)
    return expected


def _to_adu(photons: np.ndarray, camera: Camera, rng) -> np.ndarray:
    electrons = rng.poisson(photons) + rng.normal(0.0, camera.readnoise, photons.shape)
    return electrons / camera.gain + camera.offset


def make_data(
    size: str = "small",
    *,
    seed: int = 0,
    microscope: Microscope | None = None,
    fields: AberrationFields | None = None,
    camera: Camera | None = None,
    background: float = 2.0,
    bead_nm: float = 100.0,
    test_photons: tuple[float, float] = (1e3, 1e4),
    n_frames: int | None = None,
) -> ValidationData:
    """Simulate one study of the given :data:`SIZES` entry (``seed`` fixes everything).

    Test emitters have log-uniform photon counts in ``test_photons`` and a uniform defocus
    within the size's ``test_half_nm`` in every frame; ``n_frames`` test frames (default: the
    size's).
    """
    if size not in SIZES:
        raise ValueError(f"Expected `size` to be one of {tuple(SIZES)}, got {size!r}.")
    if n_frames is not None and n_frames < 1:
        raise ValueError(f"Expected `n_frames` >= 1, got {n_frames}.")
    p = SIZES[size] if n_frames is None else {**SIZES[size], "n_frames": int(n_frames)}
    rng = np.random.default_rng(seed)
    microscope = Microscope() if microscope is None else microscope
    n = p["field_px"]
    if fields is None:
        fields = AberrationFields.random((n, n), seed=seed, pixel_size_nm=microscope.pixel_size_nm)
    if camera is None:
        camera = Camera(offset=100.0, gain=0.5, readnoise=1.5,
                        pixel_size_nm=microscope.pixel_size_nm)  # fmt: skip
    return simulate_study(p, microscope, fields, camera, rng, background=background,
                          bead_nm=bead_nm, test_photons=test_photons)  # fmt: skip


def _calibration_stacks(layout: dict, microscope: Microscope, fields: AberrationFields,
                        camera: Camera, z: np.ndarray, background: float, bead_nm: float,
                        rng) -> tuple[list, list, pd.DataFrame]:  # fmt: skip
    """Calibration stacks (ADU), the same without noise (photons), and their truth table."""
    n, stacks, clean, rows = layout["field_px"], [], [], []
    for k in range(layout["n_stacks"]):
        shift = 0.25 + 0.5 * k / max(layout["n_stacks"] - 1, 1)
        points = _grid(layout["grid"], n, shift, 0.1, rng)
        expected = np.full((z.size, n, n), float(background))
        for x, y in points:
            height = float(fields.substrate_nm(x, y))
            defocus = height + z - fields.focal_surface_nm(x, y)
            patch = render_patches(microscope, fields, x, y, defocus, layout["patch_px"],
                                   bead_nm=bead_nm)  # fmt: skip
            _add(expected, layout["photons"] * patch, x, y)
            rows.append((len(rows), k, x, y, layout["photons"], height))
        stacks.append(_to_adu(expected, camera, rng))
        clean.append(expected)
    truth = pd.DataFrame(rows, columns=["particle", "stack", "x", "y", "photons",
                                        "substrate_nm"])  # fmt: skip
    return stacks, clean, truth


def _test_places(layout: dict, calibration: pd.DataFrame, rng) -> np.ndarray:
    """(n_test, 2) places of the test emitters: a jittered grid of their own, none within 3 px
    of a calibration particle (test emitters are never copies of calibration particles)."""
    side = layout.get("test_grid", layout["grid"])
    points = _grid(side, layout["field_px"], 0.5, 0.12, rng)
    gap = points[:, None, :] - calibration[["x", "y"]].to_numpy()[None]
    points = points[np.hypot(gap[..., 0], gap[..., 1]).min(axis=1) > 3.0]
    return points[rng.choice(len(points), min(layout["n_test"], len(points)), replace=False)]


def simulate_study(
    layout: dict,
    microscope: Microscope,
    fields: AberrationFields,
    camera: Camera,
    rng: np.random.Generator,
    *,
    background: float,
    bead_nm: float,
    test_photons: tuple[float, float],
) -> ValidationData:
    """Calibration stacks and test frames of one study laid out as a :data:`SIZES` entry
    (optionally with ``test_grid``, the side of the test emitters' grid)."""
    z = np.arange(-layout["z_half_nm"], layout["z_half_nm"] + layout["z_step_nm"] / 2,
                  layout["z_step_nm"])  # fmt: skip
    stacks, clean, cal_truth = _calibration_stacks(layout, microscope, fields, camera, z,
                                                   background, bead_nm, rng)  # fmt: skip
    points = _test_places(layout, cal_truth, rng)
    lo, hi = np.log(test_photons[0]), np.log(test_photons[1])
    photons = np.exp(rng.uniform(lo, hi, len(points)))
    half, n_frames = layout["test_half_nm"], layout["n_frames"]
    defocus = rng.uniform(-half, half, (len(points), n_frames))
    test_rows = [(e, f, x, y, photons[e], defocus[e, f])
                 for e, (x, y) in enumerate(points) for f in range(n_frames)]  # fmt: skip
    test_truth = pd.DataFrame(test_rows, columns=["emitter", "frame", "x", "y", "photons",
                                                  "defocus_nm"])  # fmt: skip
    n = layout["field_px"]
    expected = emitter_images(microscope, fields, test_truth, (n, n), background,
                              layout["patch_px"])  # fmt: skip
    return ValidationData(
        microscope=microscope,
        fields=fields,
        camera=camera,
        stacks=stacks,
        expected=clean,
        z_nm=z,
        calibration_truth=cal_truth,
        frames=_to_adu(expected, camera, rng),
        test_truth=test_truth,
        background=float(background),
        bead_nm=float(bead_nm),
    )

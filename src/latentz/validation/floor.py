"""The oracle floor of a validation study: each test emitter's exact local model at its place.

The floor is the z error that latentz's method would reach with perfect knowledge of the field:
every test emitter is imaged through the calibration's planes at its own place, as a point
calibration particle on a flat plane normal to the optical axis, with the calibration particles'
photons and the camera's noise, as a calibration particle exactly at the emitter's place would
be (on noise-free stacks latentz's calibration rejected most particles, as failed fits or
without a monotonic range); these stacks, over the central :data:`SPAN` of the stack's range
(which holds every test spot), are calibrated as latentz calibrates (the shape and ROI that the
calibration under test chose, ``field_model="nearest"``), and each test spot is localized with
its own emitter's model. It is scored against the same geometric truth
(:func:`latentz.validation.truth.score`). It is a reference to compare with, not a truth.

:func:`emitter_fits` and :func:`bead_fits` give latentz's fits of noise-free images, for
diagnostics.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz.validation.datasets import ValidationData, _add, _to_adu, render_patches
from latentz.validation.truth import score

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["SPAN", "bead_fits", "emitter_fits", "oracle_floor", "own_model_stacks"]

#: Share of the stack's half-range that the floor's stacks span: the test spots lie within 2/3
#: of it, and the outermost planes, where the spot outgrows the ROI, are left out.
SPAN = 0.85


def _fit_at(images: np.ndarray, x_px: float, y_px: float, roi_size: int) -> pd.DataFrame:
    """Fits (field pixels) of noise-free ``images`` (m, H, W) photons in the ROI that
    ``localize`` would centre on (x, y), moved inside the frame at its edges."""
    from latentz.fit import fit_rois

    half = roi_size // 2
    h, w = images.shape[1:]
    r0 = int(np.clip(np.rint(y_px) - half, 0, h - roi_size))
    c0 = int(np.clip(np.rint(x_px) - half, 0, w - roi_size))
    fit = fit_rois(images[:, r0 : r0 + roi_size, c0 : c0 + roi_size])
    return fit.assign(x=fit["x"] + c0, y=fit["y"] + r0)


def emitter_fits(
    data: ValidationData,
    x_px: float,
    y_px: float,
    defocus_nm: np.ndarray,
    *,
    roi_size: int,
    photons: float = 1e5,
) -> pd.DataFrame:
    """Fits of one point emitter of ``photons`` at (x, y) px alone on the background, noise-free,
    at each defocus (nm from the focal surface), in the ROI that ``localize`` would centre on it."""
    h, w = data.frames.shape[1:]
    images = np.full((len(defocus_nm), h, w), data.background)
    _add(images, photons * render_patches(data.microscope, data.fields, x_px, y_px, defocus_nm,
                                          roi_size), x_px, y_px)  # fmt: skip
    return _fit_at(images, x_px, y_px, roi_size)


def bead_fits(data: ValidationData, bead: int, *, roi_size: int) -> pd.DataFrame:
    """Fits of calibration bead ``bead`` (a ``calibration_truth`` row) in its noise-free stack,
    one per plane of ``data.z_nm``, in the ROI centred on its true position."""
    row = data.calibration_truth.iloc[bead]
    return _fit_at(data.expected[int(row["stack"])], row["x"], row["y"], roi_size)


def own_model_stacks(
    data: ValidationData, patch_px: int, *, seed: int = 0
) -> tuple[np.ndarray, pd.DataFrame]:
    """One stack (ADU, camera noise from ``seed``) of every test emitter at its place through
    ``data.z_nm``, at the calibration particles' photons, and the emitters' table (``emitter``,
    ``x``, ``y``)."""
    emitters = data.test_truth.drop_duplicates("emitter")[["emitter", "x", "y"]]
    photons = float(data.calibration_truth["photons"].iloc[0])
    h, w = data.frames.shape[1:]
    stack = np.full((data.z_nm.size, h, w), data.background)
    for x, y in emitters[["x", "y"]].to_numpy():
        defocus = data.z_nm - data.fields.focal_surface_nm(x, y)
        _add(stack, photons * render_patches(data.microscope, data.fields, x, y, defocus,
                                             patch_px), x, y)  # fmt: skip
    return _to_adu(stack, data.camera, np.random.default_rng(seed)), emitters.reset_index(drop=True)


def oracle_floor(
    data: ValidationData, cal: Calibration, spots: pd.DataFrame, *, patch_px: int
) -> pd.DataFrame:
    """:func:`~latentz.validation.truth.score` of ``spots`` (``localize_test`` output) localized
    with their own emitter's exact model (module notes); spots whose emitter the floor's
    calibration did not keep are left out."""
    from latentz.calibration import calibrate

    stack, emitters = own_model_stacks(data, patch_px)
    planes = np.abs(data.z_nm) <= SPAN * np.abs(data.z_nm).max()
    floor = calibrate([stack[planes]], data.z_nm[planes], camera=data.camera, shape=cal.shape,
                      roi_size=cal.roi_size, field_model="nearest")  # fmt: skip
    kept = floor.positions[floor.kept]
    place = emitters.set_index("emitter").loc[spots["emitter"].to_numpy()][["x", "y"]].to_numpy()
    gap = np.hypot(*(place[:, None, :] - kept[None, :, :2]).transpose(2, 0, 1)).min(axis=1)
    own = spots[gap <= 1.0]
    return score(data, floor.apply(own))

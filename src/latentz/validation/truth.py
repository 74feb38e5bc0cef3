"""Ground truth for the validation microscope, in the calibration's conventions, and scoring.

Two conventions of latentz define what a "true" localization is (docs/conventions.md), and
they are definitions rather than models, so they are computed here from noise-free images:

- best focus is the peak of the fitted Gaussian amplitude A over defocus (:func:`focus_of`,
  the calibration's own definition), and z = 0 is the least-squares plane through the best
  focus (piezo z) of the particles the calibration kept (:func:`origin_plane`); so the true z
  of a test spot is its defocus from the focal surface plus the focal surface's height there,
  minus that plane through the beads' piezo best focus plus their substrate height (the
  substrate's tilt cancels);
- the true lateral position is where the emitter appears at its own best focus (the paper's
  Fig. 2a): the order-16 polynomial of its positions through focus, fitted in the ROI that
  ``localize`` uses, read at that focus.

Both fit noise-free images with :func:`latentz.fit.fit_rois`, as the calibration does; the images
come from this package's optics.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.calibration.local import LocalOptions
from latentz.calibration.local import best_focus as amplitude_peak
from latentz.calibration.polymodel import PolyModel
from latentz.validation.datasets import ValidationData, _add, render_patches

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["bead_fits", "best_focus", "emitter_fits", "focus_of", "localize_test", "origin_plane",
           "score", "study_truth"]  # fmt: skip


def focus_of(z_nm: np.ndarray, amplitude: np.ndarray) -> float:
    """Best focus (nm) of one amplitude trace by the calibration's definition
    (:func:`latentz.calibration.local.best_focus`, the peak of an order-5 polynomial fitted
    around the amplitude's maximum). The definition is shared, not re-implemented: at low NA
    the amplitude's peak is broad, and two fitting windows that both follow the paper move it
    by tens of nm, which would show up as z error that is only a difference of conventions."""
    z = np.asarray(z_nm, dtype=float)[None, :]
    return float(amplitude_peak(z, np.asarray(amplitude, dtype=float)[None, :])[1][0])


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


def best_focus(data: ValidationData, *, roi_size: int) -> tuple[np.ndarray, pd.DataFrame]:
    """Best focus of the calibration beads and of the test emitters (:func:`focus_of`).

    Returns the beads' piezo z of best focus (one per ``calibration_truth`` row, from the
    noise-free stacks) and, per test emitter, its defocus of best focus (``focus_nm``, from the
    focal surface) and its apparent position there (``focus_x``, ``focus_y``, px: the order-16
    polynomial of its positions through focus at that defocus, as the calibration's Δx', Δy'
    are measured from; a single image's fit there wiggles by several nm with the PSF's rings),
    from noise-free images at the calibration's planes taken as defocus. The same planes matter: at
    low NA the amplitude can stay above the fitting window's threshold over a shorter range,
    and the peak of a polynomial fitted over another window is another best focus.
    """
    beads = np.array(
        [
            focus_of(data.z_nm, bead_fits(data, k, roi_size=roi_size)["amplitude"].to_numpy())
            for k in range(len(data.calibration_truth))
        ]
    )
    grid = data.z_nm - np.mean(data.z_nm)
    order = LocalOptions().lateral_order
    rows = []
    emitters = data.test_truth.drop_duplicates("emitter")
    for e, x, y in zip(emitters["emitter"], emitters["x"], emitters["y"], strict=True):
        fits = emitter_fits(data, x, y, grid, roi_size=roi_size)
        focus = focus_of(grid, fits["amplitude"].to_numpy())
        at = [
            PolyModel.from_estimate(grid[None, :], fits[axis].to_numpy()[None, :], order=order)(
                np.array([[focus]])
            )[0, 0]
            for axis in ("x", "y")
        ]
        rows.append((e, focus, *at))
    return beads, pd.DataFrame(rows, columns=["emitter", "focus_nm", "focus_x", "focus_y"])


def _plane(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    design = np.column_stack([np.ones(x.size), x, y])
    return np.linalg.lstsq(design, z, rcond=None)[0]


def localize_test(
    data: ValidationData,
    *,
    roi_size: int | None = None,
    max_px: float = 2.0,
    calibration: Calibration | None = None,
) -> pd.DataFrame:
    """Detect and fit the test frames with :func:`latentz.localization.localize` (with
    ``calibration``, its ROI unless ``roi_size`` is given, and its 3D localizations); keep
    converged, isolated spots matched to an emitter within ``max_px`` (``emitter`` column)."""
    from latentz.localization import localize

    found = localize(data.frames, calibration=calibration, camera=data.camera, roi_size=roi_size)
    found = found[found["converged"] & ~found["close_pair"] & ~found["edge"]]
    emitters = data.test_truth.drop_duplicates("emitter")
    dist, idx = cKDTree(emitters[["x", "y"]].to_numpy()).query(found[["x", "y"]].to_numpy())
    near = dist <= max_px
    return found[near].assign(emitter=emitters["emitter"].to_numpy()[idx[near]])


def score(
    data: ValidationData, located: pd.DataFrame, truth: dict[str, Any], calibration: Calibration
) -> pd.DataFrame:
    """Errors of ``calibration.apply`` output against the truth: one row per spot.

    ``truth`` is :func:`study_truth`'s; z = 0 is :func:`origin_plane` of ``calibration``.
    Columns: ``emitter``, ``frame``, ``x``, ``y`` (px),
    ``true_z_nm``, ``in_range``, ``err_x_nm``, ``err_y_nm``, ``err_z_nm`` and the reported
    ``x_err_nm``, ``y_err_nm``, ``z_err_nm``.
    """
    key = ["emitter", "frame"]
    spots = located.merge(data.test_truth, on=key, suffixes=("", "_true"))
    focus = truth["test_focus"].set_index("emitter").loc[spots["emitter"].to_numpy()]
    c0, cx, cy = origin_plane(data, truth, calibration)
    tx, ty = spots["x_true"].to_numpy(), spots["y_true"].to_numpy()
    surface = data.fields.focal_surface_nm(tx, ty)
    true_z = spots["defocus_nm"].to_numpy() + surface - (c0 + cx * tx + cy * ty)
    px = data.camera.pixel_size_nm
    return pd.DataFrame(
        {
            "emitter": spots["emitter"],
            "frame": spots["frame"],
            "x": tx,
            "y": ty,
            "true_z_nm": true_z,
            "in_range": spots["in_range"].to_numpy(bool),
            "err_x_nm": spots["x_nm"].to_numpy() - focus["focus_x"].to_numpy() * px,
            "err_y_nm": spots["y_nm"].to_numpy() - focus["focus_y"].to_numpy() * px,
            "err_z_nm": spots["z_nm"].to_numpy() - true_z,
            "x_err_nm": spots["x_err_nm"].to_numpy(),
            "y_err_nm": spots["y_err_nm"].to_numpy(),
            "z_err_nm": spots["z_err_nm"].to_numpy(),
        }
    )


def study_truth(data: ValidationData, *, roi_size: int) -> dict[str, Any]:
    """Best focus of every calibration bead and test emitter (:func:`best_focus`):
    ``bead_focus_nm`` (one per ``calibration_truth`` row) and ``test_focus``."""
    beads, test_focus = best_focus(data, roi_size=roi_size)
    return {"bead_focus_nm": beads, "test_focus": test_focus}


def origin_plane(
    data: ValidationData, truth: dict[str, Any], calibration: Calibration, *, max_px: float = 1.0
) -> np.ndarray:
    """The calibration's z = 0 in truth: ``(c0, cx, cy)`` of the least-squares plane
    ``z = c0 + cx x + cy y`` (x, y in px, nm) through the noise-free piezo best focus plus
    substrate height of the beads that ``calibration`` kept (matched within ``max_px``).

    Best focus moves by hundreds of nm across this microscope's field in no planar way, so a
    plane through another set of beads (those at the frame's edge, say, which no calibration can
    measure) is another z = 0: a convention, not an error of the calibration.
    """
    cal = data.calibration_truth
    kept = calibration.particles.iloc[calibration.kept][["x", "y"]].to_numpy()
    dist, idx = cKDTree(kept).query(cal[["x", "y"]].to_numpy())
    use = dist <= max_px
    if use.sum() < 3:
        raise ValueError(f"Only {use.sum()} kept calibration particles match a bead of the truth.")
    level = truth["bead_focus_nm"] + cal["substrate_nm"].to_numpy()  # the substrate's tilt cancels
    return _plane(cal["x"].to_numpy()[use], cal["y"].to_numpy()[use], level[use])

"""Ground truth of the validation microscope from geometry alone, and scoring.

Nothing here calls latentz's calibration or fitting: the truth is where the simulation put each
test emitter.

- Axially, the true z of a test spot is the emitter's position along the optical axis relative
  to the plane through the vertex of the focal surface, ``defocus_nm`` (its defocus from the
  curved focal surface in that frame) plus the focal surface's height at its place. The
  calibration's z = 0 is the calibration particles' surface of best focus after its plane is
  removed; that surface is where the substrate lies, so a particle on a flat plane normal to the
  axis has one z everywhere (docs/conventions.md), and the true z differs from the calibrated
  one by a plane only: the substrate's tilt, and the mean best focus of the optics.
- Laterally, the true position is where the emitter is, imaged by the optics (one pixel is
  ``pixel_size_nm`` in the sample, no distortion).

:func:`score` removes, per axis, the least-squares plane ``a + b x + c y`` of the errors over the
spots that ``apply`` found in range (one global offset and one plane: a tilt and a field-linear
focus shift cannot be told apart) and nothing else.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.validation.datasets import ValidationData

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["coverage_interval", "localize_test", "remove_planes", "score", "summary",
           "true_positions"]  # fmt: skip


def true_positions(data: ValidationData) -> pd.DataFrame:
    """Per test spot (``test_truth`` row): ``emitter``, ``frame``, and the true ``x_nm``, ``y_nm``
    (the emitter's place) and ``z_nm`` (defocus plus the focal surface's height there)."""
    t = data.test_truth
    x, y = t["x"].to_numpy(), t["y"].to_numpy()
    px = data.microscope.pixel_size_nm
    z = t["defocus_nm"].to_numpy() + data.fields.focal_surface_nm(x, y)
    return pd.DataFrame({"emitter": t["emitter"].to_numpy(), "frame": t["frame"].to_numpy(),
                         "x_nm": x * px, "y_nm": y * px, "z_nm": z})  # fmt: skip


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


#: Robust scales (1.4826 × the median absolute residual) beyond which a spot's error does not
#: set the plane: a normal error lies that far off once in 1.7 million.
GROSS_SCALES = 5.0


def remove_planes(errors: pd.DataFrame) -> pd.DataFrame:
    """``errors`` with one plane in (x, y) of each of ``err_x_nm``, ``err_y_nm``, ``err_z_nm``
    removed, fitted over the finite in-range rows (:func:`robust_plane`)."""
    out = errors.copy()
    for axis in "xyz":
        column = f"err_{axis}_nm"
        values = out[column].to_numpy(float)
        use, design = _plane_rows(errors, axis)
        if use.sum() >= 3:
            out[column] = values - design @ robust_plane(design[use], values[use])
    return out


def robust_plane(design: np.ndarray, values: np.ndarray, *, rounds: int = 10) -> np.ndarray:
    """Coefficients of the least-squares plane (``design`` (n, 3): 1, x, y) of ``values`` (n,)
    over the rows within :data:`GROSS_SCALES` robust scales of it, refitted until those rows
    stay the same. The plane is what latentz cannot know (where its z = 0 and its axes lie);
    a few gross errors (spots read microns off, on the wrong side of a shape's turn) would
    otherwise set it and shift every other spot's error. They are still scored in full."""
    keep = np.ones(len(values), bool)
    for _ in range(rounds):
        coef = np.linalg.lstsq(design[keep], values[keep], rcond=None)[0]
        resid = values - design @ coef
        scale = 1.4826 * np.median(np.abs(resid[keep] - np.median(resid[keep])))
        within = np.abs(resid) <= GROSS_SCALES * scale if scale > 0 else np.ones_like(keep)
        if within.sum() < 3 or np.array_equal(within, keep):
            break
        keep = within
    return coef


def _plane_rows(errors: pd.DataFrame, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``errors`` that ``axis``'s plane is fitted over (in range, its error finite;
    (rows,) bool) and the plane's design (rows, 3): 1, x, y (px)."""
    use = errors["in_range"].to_numpy(bool) & np.isfinite(errors[f"err_{axis}_nm"].to_numpy(float))
    x, y = errors["x"].to_numpy(), errors["y"].to_numpy()
    return use, np.column_stack([np.ones(len(errors)), x, y])


def coverage_interval(errors: pd.DataFrame, axis: str, shared_nm: float, *,
                      level: float = 0.99, draws: int = 4000,
                      seed: int = 0) -> tuple[float, float]:  # fmt: skip
    """The central ``level`` interval of the 1σ coverage on ``axis`` ("x", "y" or "z") that a
    right error model would show on a :func:`score` table: each in-range spot's error drawn as
    the reported σ says, ``shared_nm`` of it (nm, in quadrature) one draw per emitter, common
    to all its spots, the rest its own, and one plane removed over the same spots as
    :func:`remove_planes` removes it.

    A part that an emitter's spots share moves all of them together, so a table of few
    emitters scatters in coverage far more than its spots' count says, and the plane fitted to
    them takes a share of that part off: with 24 spots of 6 emitters the coverage of right
    errors averages well above 68 %."""
    used, design = _plane_rows(errors, axis)
    table, design = errors[used], design[used]
    sigma = table[f"{axis}_err_nm"].to_numpy(float)
    shared = np.minimum(shared_nm, sigma)
    own = np.sqrt(sigma**2 - shared**2)
    emitter = np.unique(table["emitter"].to_numpy(), return_inverse=True)[1].ravel()
    rng = np.random.default_rng(seed)
    drawn = (shared * rng.standard_normal((draws, emitter.max() + 1))[:, emitter]
             + own * rng.standard_normal((draws, len(table))))  # fmt: skip
    if len(table) >= 3:  # normal errors lie within GROSS_SCALES: the plane is least squares
        drawn -= drawn @ design @ np.linalg.pinv(design)
    cover = np.mean(np.abs(drawn) <= sigma, axis=1)
    tail = (1 - level) / 2
    return float(np.quantile(cover, tail)), float(np.quantile(cover, 1 - tail))


def score(data: ValidationData, located: pd.DataFrame) -> pd.DataFrame:
    """Errors of ``Calibration.apply`` output (with ``emitter`` and ``frame``) against the truth
    of :func:`true_positions`, one plane per axis removed (:func:`remove_planes`).

    Columns: ``emitter``, ``frame``, ``x``, ``y`` (true, px), ``true_z_nm``, ``in_range``,
    ``err_x_nm``, ``err_y_nm``, ``err_z_nm`` and the reported ``x_err_nm``, ``y_err_nm``,
    ``z_err_nm``.
    """
    key = ["emitter", "frame"]
    truth = true_positions(data)
    spots = located.merge(truth, on=key, suffixes=("", "_true"))
    px = data.microscope.pixel_size_nm
    errors = pd.DataFrame(
        {
            "emitter": spots["emitter"].to_numpy(),
            "frame": spots["frame"].to_numpy(),
            "x": spots["x_nm_true"].to_numpy() / px,
            "y": spots["y_nm_true"].to_numpy() / px,
            "true_z_nm": spots["z_nm_true"].to_numpy(),
            "in_range": spots["in_range"].to_numpy(bool),
            **{f"err_{a}_nm": spots[f"{a}_nm"].to_numpy() - spots[f"{a}_nm_true"].to_numpy()
               for a in "xyz"},  # fmt: skip
            **{f"{a}_err_nm": spots[f"{a}_err_nm"].to_numpy() for a in "xyz"},
        }
    )
    return remove_planes(errors)


def summary(errors: pd.DataFrame) -> dict[str, float]:
    """RMS errors (nm) and the share of |error| within the reported 1σ per axis, over the
    in-range spots of :func:`score`; ``spots`` counts them and ``in_range`` is their share."""
    used = errors[errors["in_range"].to_numpy(bool)]
    row = {"spots": float(len(used)),
           "in_range": float(errors["in_range"].mean()) if len(errors) else np.nan}  # fmt: skip
    for axis in "xyz":
        err = used[f"err_{axis}_nm"].to_numpy(float)
        sigma = used[f"{axis}_err_nm"].to_numpy(float)
        row[f"rmse_{axis}"] = float(np.sqrt(np.mean(err**2))) if err.size else np.nan
        row[f"cover_{axis}"] = float(np.mean(np.abs(err) <= sigma)) if err.size else np.nan
    return row

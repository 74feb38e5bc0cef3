"""Through-focus traces of calibration particles (paper Methods, Fig. 2).

Each particle is found once per stack, on the maximum projection over z, and followed through focus
with a ROI that stays fixed: centred on the particle across the stack and never re-detected per
plane. Every ROI of a stack is fitted in one ``fit_rois`` batch.

Particles of all stacks (stage positions) are pooled into one field: each stack's offset, the
field position of its pixel [0, 0], is added to the positions of its particles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.validate import check_array, check_int, check_positive
from latentz.calibration.dimming import DIM_COLUMNS, dim_fits
from latentz.camera import Camera
from latentz.fit.api import CORRELATION_COLUMNS

__all__ = ["Traces", "find_particles", "extract_traces", "TRACE_COLUMNS"]

#: Per-plane fit results kept in a :class:`Traces` (the ``fit_rois`` columns that calibration uses).
TRACE_COLUMNS = (
    "x",
    "y",
    "amplitude",
    "background",
    "wx",
    "wy",
    "rho",
    "photons",
    "x_err",
    "y_err",
    "amplitude_err",
    "wx_err",
    "wy_err",
    "rho_err",
    *CORRELATION_COLUMNS,
)


@dataclass(frozen=True, eq=False)
class Traces:
    """Per-plane fit results of ``n`` particles through ``n_z`` planes.

    Parameters
    ----------
    z_nm : ndarray (n_z,)
        Piezo position of each plane, strictly increasing, in nm.
    data : dict of str -> ndarray (n, n_z)
        Fit results (:data:`TRACE_COLUMNS`); ``x``, ``y`` in pixels of the pooled field (stack
        offsets included). ``converged`` (bool) marks the fits to use; NaN marks missing values.
    stack : ndarray of int (n,)
        Index of the stack each particle came from.
    offset_px : ndarray (n, 2)
        (x, y) field offset of the particle's stack (already included in ``x``, ``y``).
    crowded : ndarray of bool (n,)
        Another particle lies inside this particle's ROI.
    """

    z_nm: np.ndarray
    data: dict[str, np.ndarray]
    stack: np.ndarray = field(default=None)
    crowded: np.ndarray = field(default=None)
    offset_px: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        z = np.asarray(self.z_nm, dtype=np.float64)
        data = {}
        for name in (*TRACE_COLUMNS, *DIM_COLUMNS, "converged"):
            if name not in self.data:
                optional = name.endswith(("_err", "_corr"))
                if name in ("converged", "photons", *DIM_COLUMNS) or optional:
                    continue
                raise ValueError(f"Traces need a {name!r} array.")
            arr = np.asarray(self.data[name])
            if arr.ndim != 2 or arr.shape[1] != z.size:
                raise ValueError(
                    f"Expected trace {name!r} to have shape (n, {z.size}), got {arr.shape}."
                )
            data[name] = arr
        n = data["x"].shape[0]
        ok = np.ones((n, z.size), bool) if "converged" not in data else data["converged"]
        for name in (*TRACE_COLUMNS, *DIM_COLUMNS):
            if name in data:
                data[name] = np.where(ok, data[name].astype(np.float64), np.nan)
        data["converged"] = ok.astype(bool)
        stack = np.zeros(n, int) if self.stack is None else np.asarray(self.stack, dtype=int)
        crowded = np.zeros(n, bool) if self.crowded is None else np.asarray(self.crowded, bool)
        offset = np.zeros((n, 2)) if self.offset_px is None else np.asarray(self.offset_px, float)
        if stack.shape != (n,) or crowded.shape != (n,) or offset.shape != (n, 2):
            raise ValueError(f"Traces of {n} particles need `stack`, `crowded`, `offset_px` rows.")
        object.__setattr__(self, "offset_px", offset)
        object.__setattr__(self, "z_nm", z)
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "stack", stack)
        object.__setattr__(self, "crowded", crowded)

    def __len__(self) -> int:
        return self.data["x"].shape[0]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[name]

    def subset(self, index: Any) -> Traces:
        """Traces of the selected particles."""
        return Traces(
            self.z_nm,
            {k: v[index] for k, v in self.data.items()},
            stack=self.stack[index],
            crowded=self.crowded[index],
            offset_px=self.offset_px[index],
        )

    def planes(self, index: Any) -> Traces:
        """Traces restricted to the selected planes (for example the odd planes)."""
        return Traces(
            self.z_nm[index],
            {k: v[:, index] for k, v in self.data.items()},
            stack=self.stack,
            crowded=self.crowded,
            offset_px=self.offset_px,
        )

    def as_point_emitters(self, particle_diameter_nm: float, pixel_size_nm: float) -> Traces:
        """These traces as a point emitter at each particle's centre would have given them.

        A uniform ball of diameter d images as the PSF convolved with its projection, which adds
        d²/20 to the image's variance along every axis and leaves its covariance and photons
        unchanged. So d²/20 (in px², ``pixel_size_nm``) is taken off wx² and wy² of every fit
        (the dimmed refits' too), ρ keeps the covariance ρ wx wy, the amplitude keeps the photons
        (A ∝ 1 / √det Σ), and the errors of wx, wy, ρ and A follow to first order (their
        correlations are kept). A fit narrower than the blur along an axis becomes unmeasured
        (NaN, not converged).
        """
        blur_px2 = check_positive("particle_diameter_nm", particle_diameter_nm) ** 2 / 20.0
        blur_px2 /= check_positive("pixel_size_nm", pixel_size_nm) ** 2
        data = dict(self.data)
        fits = [""] + sorted({name[: -len("wx")] for name in DIM_COLUMNS if name.endswith("_wx")})
        for prefix in fits:
            if f"{prefix}wx" not in data:
                continue
            wx, wy, rho, amp = (data[f"{prefix}{k}"] for k in ("wx", "wy", "rho", "amplitude"))
            with np.errstate(invalid="ignore"):
                wx2, wy2 = wx**2 - blur_px2, wy**2 - blur_px2
                ok = (wx2 > 0) & (wy2 > 0)
                new_wx = np.where(ok, np.copysign(np.sqrt(np.abs(wx2)), wx), np.nan)
                new_wy = np.where(ok, np.copysign(np.sqrt(np.abs(wy2)), wy), np.nan)
                narrowing = wx * wy / (new_wx * new_wy)  # (wx wy) / (wx' wy') ≥ 1
                new_rho = rho * narrowing
                ok &= np.abs(new_rho) < 1
                gain = narrowing * np.sqrt((1 - rho**2) / (1 - new_rho**2))  # A' / A
            values = {"wx": new_wx, "wy": new_wy, "rho": new_rho, "amplitude": amp * gain}
            error_scale = {"wx": wx / new_wx, "wy": wy / new_wy, "rho": narrowing,
                           "amplitude": gain}  # fmt: skip
            for name, value in values.items():
                data[f"{prefix}{name}"] = np.where(ok, value, np.nan)
                if f"{prefix}{name}_err" in data:
                    error = data[f"{prefix}{name}_err"] * np.abs(error_scale[name])
                    data[f"{prefix}{name}_err"] = np.where(ok, error, np.nan)
            if not prefix:
                data["converged"] = data["converged"] & ok
        return Traces(self.z_nm, data, stack=self.stack, crowded=self.crowded,
                      offset_px=self.offset_px)  # fmt: skip

    def position(self) -> np.ndarray:
        """Median apparent (x, y) of each particle through the stack, in pixels, shape (n, 2)."""
        return np.stack(
            [np.nanmedian(self.data["x"], axis=1), np.nanmedian(self.data["y"], axis=1)], axis=1
        )


def find_particles(
    projection: Any,
    *,
    roi_size: int,
    threshold: float | None = None,
    min_separation: int | None = None,
) -> np.ndarray:
    """Find particles on the maximum projection (over z) of a through-focus stack.

    Parameters
    ----------
    projection : array_like (H, W)
        Maximum projection of the stack, in photons (after the camera model).
    roi_size : int
        ROI side in pixels; particles whose ROI would cross the image edge are left out.
    threshold : float, optional
        Minimum peak height above the projection's median, in photons. By default, 8 robust
        standard deviations (MAD) of the smoothed projection.
    min_separation : int, optional
        Minimum distance between two peaks, in pixels (default ``roi_size // 4``, at least 1).

    Returns
    -------
    ndarray (k, 2)
        (x, y) pixel positions of the peaks, sorted by row then column.
    """
    from scipy import ndimage
    from skimage.feature import peak_local_max

    proj = ndimage.gaussian_filter(check_array("projection", projection, ndim=2).astype(float), 1.0)
    base = np.median(proj)
    noise = 1.4826 * np.median(np.abs(proj - base))
    height = (
        8.0 * max(noise, 1e-12) if threshold is None else check_positive("threshold", threshold)
    )
    sep = (
        max(roi_size // 4, 1)
        if min_separation is None
        else check_int("min_separation", min_separation, minimum=1)
    )
    half = roi_size // 2
    peaks = peak_local_max(proj - base, min_distance=sep, threshold_abs=height, exclude_border=half)
    peaks = peaks[np.lexsort((peaks[:, 1], peaks[:, 0]))]
    return peaks[:, ::-1].astype(np.float64)


def _roi_corners(positions: np.ndarray, shape: tuple[int, int], roi_size: int) -> np.ndarray:
    """Top-left (row, col) of a ROI centred on each (x, y), clipped inside the image."""
    from latentz.detect import roi_corners

    centre = np.rint(positions).astype(int)
    row0, col0, _ = roi_corners(centre[:, 1], centre[:, 0], roi_size, shape)
    return np.column_stack([row0, col0])


def _fit_stack(
    stack: np.ndarray,
    corners: np.ndarray,
    roi_size: int,
    camera: Camera,
    method: str,
    device: str = "auto",
) -> dict[str, np.ndarray]:
    """Cut the fixed ROIs of one stack (ADU), convert them to photons and fit every ROI of every
    plane in one ``fit_rois`` call."""
    from latentz.fit import fit_rois

    n_z = stack.shape[0]
    rows = corners[:, 0, None] + np.arange(roi_size)
    cols = corners[:, 1, None] + np.arange(roi_size)
    # rois[p, z] = stack[z, rows[p]][:, cols[p]] for all particles and planes at once
    rois = stack[:, rows[:, :, None], cols[:, None, :]].transpose(1, 0, 2, 3)
    photons = replace(camera, flatfield=None).to_photons(rois)
    if camera.flatfield is not None:
        photons /= camera.flatfield[rows[:, :, None], cols[:, None, :]][:, None]
    k = corners.shape[0]
    fit_camera = Camera(
        offset=0.0, gain=1.0, readnoise=camera.readnoise, pixel_size_nm=camera.pixel_size_nm
    )
    table = fit_rois(
        photons.reshape(k * n_z, roi_size, roi_size),
        method=method,
        camera=fit_camera,
        device=device,
        # the errors a spot of `localize` carries: Calibration.noise_scale compares them with
        # the scatter of these fits about the calibration curve
        errors="sandwich",
    )
    out = {}
    for name in (*TRACE_COLUMNS, "converged"):
        if name in table.columns:
            out[name] = table[name].to_numpy().reshape(k, n_z)
    params = table[["x", "y", "amplitude", "background", "wx", "wy", "rho"]].to_numpy()
    dim = dim_fits(photons.reshape(k * n_z, roi_size, roi_size), params, method=method,
                   device=device)  # fmt: skip
    out.update({name: value.reshape(k, n_z) for name, value in dim.items()})
    out["x"] = out["x"] + corners[:, 1, None]
    out["y"] = out["y"] + corners[:, 0, None]
    return out


def extract_traces(
    stacks: Sequence[Any],
    z_nm: np.ndarray,
    *,
    camera: Camera,
    roi_size: int = 15,
    positions: Sequence[Any] | None = None,
    stage_offsets_px: Any = None,
    threshold: float | None = None,
    method: str = "mle",
    progress: bool = False,
    device: str = "auto",
) -> Traces:
    """Traces of every particle of every stack, pooled into one field.

    Parameters
    ----------
    stacks : sequence of array_like (n_z, H, W)
        Through-focus stacks in ADU, one per stage position.
    z_nm : ndarray (n_z,)
        Piezo position of each plane, nm.
    camera : Camera
        Converts ADU to photons (offset, gain, flatfield); its read noise goes to the fit.
    roi_size : int
        Side of the fixed ROI, pixels.
    positions : sequence of array_like (k, 2), optional
        Explicit (x, y) pixel positions of the particles of each stack, instead of detection
        (for example a single bead in a small stack).
    stage_offsets_px : array_like (n_stacks, 2), optional
        (x, y) position of each stack's pixel [0, 0] in the pooled field, pixels. Default: all
        zero (one stack, or stacks that all cover the same field).
    threshold : float, optional
        Detection threshold, see :func:`find_particles`.
    method : str
        Fitting method passed to ``fit_rois``.
    progress : bool
        Show a progress bar over the stacks.
    device : {"auto", "cpu", "cuda"}
        Where the fits run (:func:`latentz._shared.engine.resolve_device`).
    """
    from tqdm.auto import tqdm

    roi_size = check_int("roi_size", roi_size, minimum=5)
    n_stacks = len(stacks)
    offsets = np.zeros((n_stacks, 2))
    if stage_offsets_px is not None:
        offsets = check_array("stage_offsets_px", stage_offsets_px, ndim=2).astype(np.float64)
        if offsets.shape != (n_stacks, 2):
            raise ValueError(
                f"Expected `stage_offsets_px` to have shape ({n_stacks}, 2), got {offsets.shape}."
            )
    if positions is not None and len(positions) != n_stacks:
        raise ValueError(
            f"Expected `positions` to hold one (k, 2) array per stack ({n_stacks}), "
            f"got {len(positions)}."
        )
    parts: list[dict[str, np.ndarray]] = []
    stack_index, crowded = [], []
    for s, stack in enumerate(tqdm(stacks, desc="calibration stacks", disable=not progress)):
        stack = check_array(f"stacks[{s}]", stack, ndim=3)
        if stack.shape[0] != z_nm.size:
            raise ValueError(
                f"Stack {s} has {stack.shape[0]} planes but `z_nm` has {z_nm.size} values."
            )
        if min(stack.shape[1:]) < roi_size:
            raise ValueError(
                f"Stack {s} of shape {stack.shape} is smaller than `roi_size`={roi_size}."
            )
        if positions is None:
            projection = camera.to_photons(np.max(stack, axis=0))
            found = find_particles(projection, roi_size=roi_size, threshold=threshold)
        else:
            found = check_array(f"positions[{s}]", positions[s], ndim=(1, 2), allow_empty=True)
            found = found.reshape(-1, 2).astype(np.float64)
        if found.shape[0] == 0:
            continue
        corners = _roi_corners(found, stack.shape[1:], roi_size)
        parts.append(_fit_stack(stack, corners, roi_size, camera, method, device))
        parts[-1]["x"] = parts[-1]["x"] + offsets[s, 0]
        parts[-1]["y"] = parts[-1]["y"] + offsets[s, 1]
        stack_index.append(np.full(found.shape[0], s))
        gap = np.abs(found[:, None, :] - found[None, :, :]).max(axis=2)
        np.fill_diagonal(gap, np.inf)
        crowded.append(np.any(gap <= roi_size // 2, axis=1))
    if not parts:
        raise ValueError(
            "No particles found in the calibration stack(s): check `threshold`, the camera "
            "offset and gain, or pass explicit `positions`."
        )
    data = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    stack_index = np.concatenate(stack_index)
    return Traces(
        z_nm,
        data,
        stack=stack_index,
        crowded=np.concatenate(crowded),
        offset_px=offsets[stack_index],
    )


def traces_table(traces: Traces) -> pd.DataFrame:
    """Long table (one row per particle and plane), for export and figures."""
    n, n_z = len(traces), traces.z_nm.size
    table = {"particle": np.repeat(np.arange(n), n_z), "z_nm": np.tile(traces.z_nm, n)}
    table.update({k: v.ravel() for k, v in traces.data.items()})
    return pd.DataFrame(table)

"""The calibration pipeline: stacks → traces → local models → culling → tilt removal.

:func:`calibrate` turns through-focus stacks of calibration particles into a
:class:`~latentz.calibration.calibration.Calibration`: traces of every particle, its local models
(z_f, Δx'(z), Δy'(z), z(shape) with σ's), culling of defective particles, and removal of the
substrate tilt so that z = 0 is the focal surface of the calibration particles after levelling.
Only ``field_model="nearest"`` is available until the widefield stage is integrated.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.sanity import LatentzWarning, check_z_step
from latentz._shared.validate import check_array, check_choice, check_int, check_positive
from latentz.calibration.calibration import FIELD_MODELS, PAPER_SHAPES, Calibration
from latentz.calibration.culling import cull as cull_particles
from latentz.calibration.culling import particle_features
from latentz.calibration.local import LocalOptions, fit_local
from latentz.calibration.shape import SHAPES, astigmatism_angle
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import Traces, extract_traces
from latentz.camera import Camera
from latentz.engine import resolve_device

__all__ = ["calibrate", "calibrate_traces"]

#: Fewer usable particles than this make population statistics meaningless: only outright
#: failures are culled then.
_MIN_POPULATION = 10


def _check_z(z_nm: Any, options: LocalOptions) -> np.ndarray:
    z = check_array("z_nm", z_nm, ndim=1, dtype_kind="uif").astype(np.float64)
    if not np.all(np.isfinite(z)):
        raise ValueError("Expected `z_nm` to be finite everywhere.")
    need = max(options.lateral_order, options.shape_order, options.amplitude_order) + 2
    if z.size < need:
        raise ValueError(
            f"The calibration needs at least {need} planes for polynomials of order "
            f"{need - 2} (lateral_order/shape_order), got {z.size} values in `z_nm`."
        )
    steps = np.diff(z)
    if not (np.all(steps > 0) or np.all(steps < 0)):
        raise ValueError(
            "Expected `z_nm` to be strictly monotonic (one piezo position per plane, in order)."
        )
    return z


def _local_options(options: dict[str, Any]) -> LocalOptions:
    fields = LocalOptions.__dataclass_fields__
    chosen = {k: options.pop(k) for k in list(options) if k in fields}
    for name in ("amplitude_order", "lateral_order", "shape_order"):
        if name in chosen:
            check_int(name, chosen[name], minimum=1)
    for name in ("focus_fraction", "sigma_window_nm", "min_range_nm"):
        if name in chosen:
            check_positive(name, chosen[name])
    return LocalOptions(**chosen)


def calibrate(
    stacks: Any,
    z_nm: Any,
    *,
    camera: Camera | None = None,
    shape: str = "rho_A",
    field_model: str = "zernike",
    n_terms: int = 400,
    progress: bool = False,
    roi_size: int = 15,
    positions: Sequence[Any] | None = None,
    stage_offsets_px: Any = None,
    threshold: float | None = None,
    method: str = "mle",
    device: str = "auto",
    **options: Any,
) -> Calibration:
    """Calibrate the microscope from through-focus stacks of fluorescent particles.

    Parameters
    ----------
    stacks : array_like (n_z, H, W), path, or a sequence of them
        Through-focus stacks in ADU, one per stage position.
    z_nm : array_like (n_z,)
        Piezo position of each plane (shared by all stacks), strictly monotonic, nm.
    camera : Camera, optional
        Camera model (default ``Camera()``); its pixel size converts positions to nm.
    shape : {"rho", "rho_w", "rho_A", "auto", "auto_A"}
        Shape parameter for axial localization (paper eqs. 4–6; "auto" for any astigmatism angle).
    field_model : {"zernike", "natural", "nearest"}
        How the local models are carried across the field (Supp. Table 2): Zernike
        polynomials fitted by least squares, natural-neighbour or nearest-neighbour
        interpolation.
    n_terms : int
        Number of Zernike terms (for ``field_model="zernike"``).
    progress : bool
        Show a progress bar.
    roi_size : int
        Side of the fixed ROI that follows each particle through focus, pixels.
    positions : sequence of array_like (k, 2), optional
        Explicit (x, y) pixel positions of the particles in each stack instead of detection,
        for example ``[[(10, 10)]]`` for a stack holding a single bead.
    stage_offsets_px : array_like (n_stacks, 2), optional
        (x, y) position of each stack's pixel [0, 0] in the pooled field, pixels; spots given to
        :meth:`Calibration.apply` are in the same field pixels.
    threshold : float, optional
        Detection threshold in photons above the projection's median.
    method : {"mle", "wlsq", "lsq"}
        Gaussian fitting method.
    device : {"auto", "cpu", "cuda"}
        Where the fits run: CPU or GPU (numba's CUDA target, extra ``latentz[gpu]``).
    **options
        ``tilt`` (bool, default True): fit and remove the substrate tilt;
        ``cull`` (bool, default True) and ``cull_threshold`` (robust z-score, default 6),
        ``neighbours`` (default 8) — with fewer than 10 usable particles only outright failures
        are culled, as population statistics need a population; and the
        :class:`~latentz.calibration.local.LocalOptions` fields (``amplitude_order``,
        ``focus_fraction``, ``lateral_order``, ``shape_order``,
        ``sigma_window_nm``, ``min_range_nm``).

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        Too few planes for the polynomial orders, non-monotonic ``z_nm``, or no particles.
    """
    camera = Camera() if camera is None else camera
    if not isinstance(camera, Camera):
        raise TypeError(f"Expected `camera` to be a latentz Camera, got {type(camera).__name__}.")
    local_options = _local_options(dict(options))
    z = _check_z(z_nm, local_options)
    check_choice("shape", shape, SHAPES)
    check_choice("field_model", field_model, FIELD_MODELS)
    device = resolve_device(device)
    if isinstance(stacks, (str, os.PathLike)) or (hasattr(stacks, "ndim") and stacks.ndim == 3):
        stacks = [stacks]
    loaded = []
    for s, stack in enumerate(stacks):
        if isinstance(stack, (str, os.PathLike)):
            from latentz.io import read_stack

            stack = read_stack(stack)
        stack = check_array(f"stacks[{s}]", stack, ndim=3)
        if stack.shape[0] != z.size:
            raise ValueError(
                f"Stack {s} has {stack.shape[0]} planes but `z_nm` has {z.size} values."
            )
        loaded.append(stack)
    order = np.argsort(z)
    loaded = [stack[order] for stack in loaded]
    traces = extract_traces(
        loaded,
        z[order],
        camera=camera,
        roi_size=roi_size,
        positions=positions,
        stage_offsets_px=stage_offsets_px,
        threshold=threshold,
        method=method,
        progress=progress,
        device=device,
    )
    if "field_shape" not in options:
        offsets = np.zeros((len(loaded), 2)) if stage_offsets_px is None else stage_offsets_px
        offsets = np.asarray(offsets, dtype=np.float64).reshape(len(loaded), 2)
        options["field_shape"] = (
            int(max(o[1] + st.shape[1] for o, st in zip(offsets, loaded, strict=True))),
            int(max(o[0] + st.shape[2] for o, st in zip(offsets, loaded, strict=True))),
        )
    return calibrate_traces(
        traces,
        camera=camera,
        shape=shape,
        field_model=field_model,
        n_terms=n_terms,
        roi_size=roi_size,
        **options,
    )


def calibrate_traces(
    traces: Traces,
    *,
    camera: Camera | None = None,
    shape: str = "rho_A",
    field_model: str = "zernike",
    n_terms: int = 400,
    tilt: bool = True,
    cull: bool = True,
    cull_threshold: float = 6.0,
    neighbours: int = 8,
    field_shape: tuple[int, int] | None = None,
    roi_size: int | None = None,
    iterations: int = 0,
    sources: Sequence[str] | None = None,
    **options: Any,
) -> Calibration:
    """Calibrate from traces already fitted (see :func:`calibrate` for the parameters).

    Useful to calibrate on a subset of planes (``traces.planes(...)``) or particles.
    """
    camera = Camera() if camera is None else camera
    local_options = _local_options(options)
    if options:
        raise TypeError(f"Unknown calibration option(s): {', '.join(sorted(options))}.")
    _check_z(traces.z_nm, local_options)
    if np.any(np.diff(traces.z_nm) <= 0):
        raise ValueError("Expected the traces' `z_nm` to be strictly increasing.")
    check_choice("shape", shape, SHAPES)
    check_choice("field_model", field_model, FIELD_MODELS)
    n_terms = check_int("n_terms", n_terms, minimum=1)
    cull_threshold = check_positive("cull_threshold", cull_threshold)
    neighbours = check_int("neighbours", neighbours, minimum=1)
    if len(traces) == 0:
        raise ValueError("No calibration particles: the traces are empty.")
    check_z_step(float(np.median(np.diff(traces.z_nm))), _width_rate(traces, camera))
    theta = None
    if shape in ("auto", "auto_A"):
        theta = astigmatism_angle(traces["wx"], traces["wy"], traces["rho"])
    shapes = tuple(dict.fromkeys((*PAPER_SHAPES, shape)))
    local = fit_local(traces, shapes, theta=theta, options=local_options)

    px = camera.pixel_size_nm
    position = traces.position()
    substrate_nm = position * px
    converged = np.mean(traces["converged"], axis=1)
    hard = {
        "fit_failed": converged < 0.8,
        "never_in_focus": ~local.in_focus,
        "crowded": traces.crowded,
        "no_monotonic_range": ~local.shapes[shape].inverse.valid,
    }
    failed = np.any(np.stack(list(hard.values())), axis=0)
    plane = _tilt_plane(substrate_nm, local.z_f, ~failed, tilt)
    culled, reason = failed, np.array([""] * len(traces), dtype=object)
    scores = pd.DataFrame(index=np.arange(len(traces)))
    if cull and np.count_nonzero(~failed) >= _MIN_POPULATION:
        shifted = local.shifted(plane(*substrate_nm.T))
        features = particle_features(traces, shifted, shape, position * px, ~failed, k=neighbours)
        culled, reason, scores = cull_particles(features, hard, threshold=cull_threshold)
        plane = _tilt_plane(substrate_nm, local.z_f, ~culled, tilt)
    else:
        reason = np.array(
            [",".join(k for k, m in hard.items() if m[i]) for i in range(len(traces))],
            dtype=object,
        )
    options_used = {
        "shape": shape,
        "field_model": field_model,
        "n_terms": n_terms,
        "tilt": tilt,
        "cull": cull,
        "cull_threshold": cull_threshold,
        "neighbours": neighbours,
        "field_shape": _field_shape(traces, field_shape),
        "roi_size": roi_size,
        "iterations": check_int("iterations", iterations, minimum=0),
        "sources": [str(x) for x in sources] if sources is not None else [],
        **{k: getattr(local_options, k) for k in LocalOptions.__dataclass_fields__},
    }
    return Calibration(
        camera=camera,
        traces=traces,
        local=local.shifted(plane(*substrate_nm.T)),
        plane=plane,
        culled=culled,
        reason=reason,
        scores=scores,
        options=options_used,
    )


def _width_rate(traces: Traces, camera: Camera) -> float:
    """Median over particles of the change of the mean fitted width (nm) between its narrowest
    and widest converged planes, per nm of z between them (NaN if none has two such planes)."""
    width = np.where(traces["converged"], (traces["wx"] + traces["wy"]) / 2, np.nan)
    usable = np.sum(np.isfinite(width), axis=1) >= 2
    if not usable.any():
        return np.nan
    width = width[usable]
    low, high = np.nanargmin(width, axis=1), np.nanargmax(width, axis=1)
    rows = np.arange(len(width))
    span = np.abs(traces.z_nm[high] - traces.z_nm[low])
    change = (width[rows, high] - width[rows, low]) * camera.pixel_size_nm
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.nanmedian(np.where(span > 0, change / span, np.nan)))


def _field_shape(traces: Traces, given: Any) -> list[int]:
    """(H, W) of the whole field in pixels: as given, else the particles' extent plus a margin."""
    if given is not None:
        return [check_int("field_shape", int(v), minimum=1) for v in given]
    pos = traces.position()
    extent = np.nanmax(pos, axis=0) if len(pos) else np.zeros(2)
    return [int(np.ceil(extent[1])) + 8, int(np.ceil(extent[0])) + 8]


def _tilt_plane(substrate_nm: np.ndarray, z_f: np.ndarray, use: np.ndarray, tilt: bool):
    """Plane of best focus over the usable particles; a flat plane at their mean z_f when the
    tilt is not wanted. Where it cannot be determined (fewer than 3 particles, or collinear
    ones) the plane is flat too, and a warning says why."""
    if not np.isfinite(z_f).any():
        raise ValueError(
            "No calibration particle has a best focus (z_f): check that the z range of the "
            "stacks covers the particles' focus."
        )
    use = use & np.isfinite(z_f)
    if not use.any():
        warnings.warn(
            "Every calibration particle failed a check; the focal plane is fitted to all "
            "particles with a best focus.",
            LatentzWarning,
            stacklevel=3,
        )
        use = np.isfinite(z_f)
    z0 = float(np.mean(z_f[use]))
    if not tilt:
        return TiltPlane.flat(z0)
    try:
        return TiltPlane.from_estimate(*substrate_nm.T, z_f, mask=use)
    except ValueError as exc:
        warnings.warn(
            f"No tilt correction: {exc} The focal plane is taken flat at z = {z0:.1f} nm; "
            "pass tilt=False to choose this.",
            LatentzWarning,
            stacklevel=3,
        )
        return TiltPlane.flat(z0)

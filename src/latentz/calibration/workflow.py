"""The calibration pipeline: stacks → traces → local models → culling → tilt removal.

:func:`calibrate` turns through-focus stacks of calibration particles into a
:class:`~latentz.calibration.result.Calibration`: traces of every particle, its local models
(z_f, Δx'(z), Δy'(z), z(shape) with σ's), culling of defective particles, and removal of the
substrate tilt so that z = 0 is the focal surface of the calibration particles after levelling.
"""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from latentz._shared.engine import resolve_device
from latentz._shared.sanity import LatentzWarning, check_z_step, warn
from latentz._shared.validate import check_array, check_choice, check_int, check_positive
from latentz.calibration.culling import cull as cull_particles
from latentz.calibration.culling import particle_features
from latentz.calibration.depth import depth_ratio_per_nm
from latentz.calibration.heights import particle_heights
from latentz.calibration.local import LocalModels, LocalOptions, fit_local, measured_run, row_mean
from latentz.calibration.result import FIELD_CHOICES, PAPER_SHAPES, Calibration
from latentz.calibration.roi import (
    MIN_ROI,
    candidate_rois,
    choose_roi,
    expected_errors,
    focus_width_px,
    frame_background,
    roi_limit,
    spacing_limit,
)
from latentz.calibration.shape import SHAPES, astigmatism_angle
from latentz.calibration.shape_choice import choose, score_shapes
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import Traces, extract_traces
from latentz.camera import Camera

__all__ = ["calibrate", "calibrate_traces"]

#: First ROI of an automatic choice (pixels): its traces give the in-focus width and spacing;
#: where it fails, ROIs this many pixels apart are tried (:func:`_probe_ladder`).
_FIRST_ROI = 15
_PROBE_STEP = 8
#: Fewer kept particles than this cannot carry models across the field.
_MIN_WIDEFIELD = 3
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
            f"The calibration needs a through-focus stack of at least {need} planes (one image "
            f"per z) to model each particle, got {z.size}: record more planes, or lower "
            f"lateral_order/shape_order (now {need - 2})."
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
    shape: str | None = None,
    field_model: str = "auto",
    n_terms: int = 400,
    progress: bool = False,
    roi_size: int | None = None,
    positions: Sequence[Any] | None = None,
    stage_offsets_px: Any = None,
    threshold: float | None = None,
    method: str = "mle",
    device: str = "auto",
    particle_diameter_nm: float | None = None,
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
    shape : {"rho", "rho_w", "rho_A", "auto", "auto_A"}, optional
        Shape parameter for axial localization (paper eqs. 4–6; "auto" for any astigmatism
        angle). None picks the one with the best expected σ_z for single molecules and for
        emitters like the calibration particles (:mod:`latentz.calibration.shape_choice`);
        ``cal.shape_choice`` says why.
    field_model : {"auto", "zernike", "natural", "curves", "nearest"}
        How models are carried across the field. "auto" (default): the best by leave-one-
        particle-out cross-validation of the whole prediction, never worse than "nearest"
        (:mod:`latentz.calibration.crossval`); chosen on first use (``cal.field_model``).
    n_terms : int
        Number of Zernike terms (for ``field_model="zernike"``).
    progress : bool
        Show a progress bar.
    roi_size : int, optional
        Side of the fixed ROI that follows each particle through focus, pixels. None
        calibrates at a few candidate sizes (from the in-focus spot's, bounded by the images
        and the particles' spacing) and keeps the one with the best cross-validated z error of
        typical emitters (:mod:`latentz.calibration.roi`); ``cal.options["roi_choice"]`` says
        why, with each candidate's figures and usable z range.
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
    particle_diameter_nm : float, optional
        Diameter of the calibration beads, nm, to read point emitters (single molecules)
        through them: each fit's d²/20 of variance per axis, the blur of a uniform ball's
        projection, is taken off before the models are built
        (:meth:`~latentz.calibration.traces.Traces.as_point_emitters`), so the calibration holds
        the shapes of a point at the beads' centres; ``cal.traces`` are those. Give it where
        the beads are not small against the PSF and the emitters are points: 100–200 nm beads
        at high NA (docs/accuracy.md, "Emitters of another size than the calibration
        particles"). None (default): the calibration holds the beads' own shapes, for tracking
        particles like them. The ROI is chosen on the beads as imaged.
    **options
        ``tilt`` (bool, default True): fit and remove the substrate tilt;
        ``heights`` (bool, default True): take each particle's own height off its models where
        its brightness predicts it (beads of unequal size; :mod:`latentz.calibration.heights`);
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
    if shape is not None:
        check_choice("shape", shape, SHAPES)
    check_choice("field_model", field_model, FIELD_CHOICES)
    if particle_diameter_nm is not None:
        check_positive("particle_diameter_nm", particle_diameter_nm)
    device = resolve_device(device)
    loaded, z = _load_stacks(stacks, z, camera)
    if "field_shape" not in options:
        options["field_shape"] = _pooled_field_shape(loaded, stage_offsets_px)
    limit = min(roi_limit(st.shape[1:]) for st in loaded)
    if roi_size is not None:
        roi_size = _check_roi_size(roi_size, loaded, limit, explicit=positions is not None)

    traces_at: dict[int, Traces] = {}

    def once(
        roi: int, model: str = field_model, diameter_nm: float | None = particle_diameter_nm
    ) -> Calibration:
        """Traces of every particle in a ``roi``-pixel ROI (fitted once per ROI), then the
        calibration from them with field model ``model`` for particles of ``diameter_nm``."""
        if roi not in traces_at:
            traces_at[roi] = extract_traces(
                loaded,
                z,
                camera=camera,
                roi_size=roi,
                positions=positions,
                stage_offsets_px=stage_offsets_px,
                threshold=threshold,
                method=method,
                progress=progress,
                device=device,
            )
        return calibrate_traces(
            traces_at[roi],
            camera=camera,
            shape=shape,
            field_model=model,
            n_terms=n_terms,
            roi_size=roi,
            method=method,
            particle_diameter_nm=diameter_nm,
            **options,
        )

    run = functools.partial(_recorded, once)
    if roi_size is not None:
        cal, caught = run(roi_size)
        _say(caught)
        return cal
    background = frame_background(loaded, camera)
    judge = functools.partial(expected_errors, stacks=loaded, camera=camera, background=background)
    # candidates are judged on the particles' own images: their shapes, not a point's
    candidate = functools.partial(
        _recorded, functools.partial(once, model="nearest", diameter_nm=None)
    )
    final = None if field_model == "nearest" and particle_diameter_nm is None else run
    return _calibrate_roi(candidate, min(_FIRST_ROI, limit), limit, judge, final)


def _load_stacks(stacks: Any, z: np.ndarray, camera: Camera) -> tuple[list[np.ndarray], np.ndarray]:
    """The stacks (arrays or paths; one or a sequence) checked against ``z`` and the camera
    offset, with their planes and ``z`` (nm) in increasing z."""
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
    _check_offset(camera, loaded)
    order = np.argsort(z)
    return [stack[order] for stack in loaded], z[order]


def _pooled_field_shape(stacks: list[np.ndarray], stage_offsets_px: Any) -> tuple[int, int]:
    """(H, W) in pixels of the field that holds every stack at its stage offset."""
    offsets = np.zeros((len(stacks), 2)) if stage_offsets_px is None else stage_offsets_px
    offsets = np.asarray(offsets, dtype=np.float64).reshape(len(stacks), 2)
    return (
        int(max(o[1] + st.shape[1] for o, st in zip(offsets, stacks, strict=True))),
        int(max(o[0] + st.shape[2] for o, st in zip(offsets, stacks, strict=True))),
    )


def _check_roi_size(roi_size: Any, stacks: list[np.ndarray], limit: int, explicit: bool) -> int:
    """``roi_size`` checked to fit the images (``limit`` pixels) unless the particles'
    positions are ``explicit``."""
    roi_size = check_int("roi_size", roi_size, minimum=MIN_ROI)
    if not explicit and roi_size > limit:
        side = min(min(st.shape[1:]) for st in stacks)
        raise ValueError(
            f"roi_size={roi_size} does not fit the {side} px calibration images (a particle "
            f"must lie a pixel inside the edge): use roi_size <= {limit}, or None."
        )
    return roi_size


def _recorded(once: Callable[[int], Calibration], roi: int) -> tuple[Calibration, list]:
    """One calibration with ``roi``, and the warnings it gave (to say once, not per pass)."""
    failure = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            cal = once(roi)
        except Exception as exc:  # said after its warnings, outside the recording
            failure = exc
    if failure is not None:
        _say(caught)
        raise failure
    return cal, caught


def _say(caught: list) -> None:
    """Issue again each distinct warning recorded in ``caught``."""
    for message in {str(w.message): w for w in caught}.values():
        warnings.warn(message.message, message.category, stacklevel=4)


def _calibrate_roi(run, first: int, limit: int, judge, final=None) -> Calibration:
    """Calibrate at each candidate ROI with ``run`` (:func:`~latentz.calibration.roi.
    candidate_rois`, from the in-focus width of a first calibration at ``first`` px, never
    above ``limit`` nor the particles' spacing) and keep the one whose calibration localizes
    typical emitters best (``judge``: :func:`~latentz.calibration.roi.expected_errors` of a
    calibration; :func:`~latentz.calibration.roi.choose_roi`), calibrated again by ``final``
    where given (the requested field model; the candidates use each particle's own models);
    ``cal.options["roi_choice"]`` says why. A candidate that fails is skipped; only when every
    one fails is its error raised."""
    runs: dict[int, tuple[Calibration, list]] = {}
    failures: dict[int, tuple[Exception, list]] = {}

    def attempt(roi: int) -> None:
        with warnings.catch_warnings(record=True) as said:  # a skipped ROI's are not said
            warnings.simplefilter("always")
            try:
                runs[roi] = run(roi)
            except ValueError as exc:
                failures[roi] = (exc, said)

    for roi in _probe_ladder(first, limit):  # the first ROI that calibrates
        attempt(roi)
        if roi in runs:
            probe = runs[roi][0].traces
            break
    else:
        exc, said = failures[first]
        _say(said)
        raise exc
    upper = min(limit, spacing_limit(probe))
    for roi in candidate_rois(focus_width_px(probe), upper):
        if roi not in runs and roi not in failures:
            attempt(roi)
    scored = {r: run_ for r, run_ in runs.items() if r <= upper} or runs
    scores = {r: judge(cal) for r, (cal, _) in scored.items()}
    chosen, record = choose_roi(scores)
    record["failed"] = {str(r): str(e) for r, (e, _) in failures.items()}
    cal, caught = runs[chosen] if final is None else final(chosen)
    _say(caught)
    cal.options["roi_choice"] = record
    cal.options["roi_size_reason"] = record["reason"]
    return cal


def _probe_ladder(first: int, limit: int) -> list[int]:
    """ROIs to try, in order, until one calibrates: ``first``, the smallest, then up to four
    larger ones :data:`_PROBE_STEP` px apart, none above ``limit`` (spots that outgrow
    ``first`` through most of the stack fail their fits there)."""
    larger = range(first + _PROBE_STEP, min(limit, first + 4 * _PROBE_STEP) + 1, _PROBE_STEP)
    return list(dict.fromkeys([first, MIN_ROI, *larger]))


def calibrate_traces(
    traces: Traces,
    *,
    camera: Camera | None = None,
    shape: str | None = None,
    field_model: str = "auto",
    n_terms: int = 400,
    tilt: bool = True,
    heights: bool = True,
    cull: bool = True,
    cull_threshold: float = 6.0,
    neighbours: int = 8,
    field_shape: tuple[int, int] | None = None,
    roi_size: int | None = None,
    method: str = "mle",
    iterations: int = 0,
    sources: Sequence[str] | None = None,
    particle_diameter_nm: float | None = None,
    **options: Any,
) -> Calibration:
    """Calibrate from traces already fitted (see :func:`calibrate` for the parameters).

    Useful to calibrate on a subset of planes (``traces.planes(...)``) or particles. With
    ``particle_diameter_nm``, ``traces`` are the particles' fits as measured: a calibration's
    own ``cal.traces`` are already those of point emitters.
    """
    camera = Camera() if camera is None else camera
    local_options = _local_options(options)
    if options:
        raise TypeError(f"Unknown calibration option(s): {', '.join(sorted(options))}.")
    _check_z(traces.z_nm, local_options)
    if np.any(np.diff(traces.z_nm) <= 0):
        raise ValueError("Expected the traces' `z_nm` to be strictly increasing.")
    if shape is not None:
        check_choice("shape", shape, SHAPES)
    check_choice("field_model", field_model, FIELD_CHOICES)
    n_terms = check_int("n_terms", n_terms, minimum=1)
    cull_threshold = check_positive("cull_threshold", cull_threshold)
    neighbours = check_int("neighbours", neighbours, minimum=1)
    if particle_diameter_nm is not None:
        particle_diameter_nm = check_positive("particle_diameter_nm", particle_diameter_nm)
        traces = traces.as_point_emitters(particle_diameter_nm, camera.pixel_size_nm)
    _check_population(traces, camera)
    theta = _astigmatism_angle(traces, shape)
    local = fit_local(traces, _candidates(shape, theta), theta=theta, options=local_options)
    px = camera.pixel_size_nm
    position = traces.position()
    substrate_nm = position * px
    hard = _hard_failures(traces, local)
    _check_kept(np.any(np.stack(list(hard.values())), axis=0), _reasons(hard), roi_size)
    choice = None
    if shape is None:
        usable = ~np.any(np.stack(list(hard.values())), axis=0)
        shape, choice = _choose_shape(traces, local, usable, tilt, camera, roi_size)
    hard["no_monotonic_range"] = ~local.shapes[shape].inverse.valid
    culled, reason, scores, plane = _cull(
        traces, local, shape, hard, tilt, px, cull=cull, threshold=cull_threshold, k=neighbours
    )
    _check_kept(culled, reason, roi_size)
    own = np.zeros(len(traces))
    height_fit: dict[str, Any] = {"applied": False}
    if heights:
        own, height_fit = particle_heights(traces, local.z_nm, local.z_f, position, ~culled,
                                           pixel_size_nm=px)  # fmt: skip
    if height_fit["applied"]:  # the focal plane of the particles at their common height
        plane = _tilt_plane(substrate_nm, local.z_f - own, ~culled, tilt)
    field_model = _field_model_for(field_model, int(np.count_nonzero(~culled)))
    options_used = {
        "shape": shape,
        "shape_choice": choice,
        "field_model": field_model,
        "n_terms": n_terms,
        "tilt": tilt,
        "heights": heights,
        "particle_heights": height_fit,
        "cull": cull,
        "cull_threshold": cull_threshold,
        "neighbours": neighbours,
        "field_shape": _field_shape(traces, field_shape),
        "roi_size": roi_size,
        "method": method,
        "iterations": check_int("iterations", iterations, minimum=0),
        "sources": [str(x) for x in sources] if sources is not None else [],
        "particle_diameter_nm": particle_diameter_nm,
        **{k: getattr(local_options, k) for k in LocalOptions.__dataclass_fields__},
    }
    cal = Calibration(
        camera=camera,
        traces=traces,
        local=local.shifted(plane(*substrate_nm.T) + own),
        plane=plane,
        culled=culled,
        reason=reason,
        scores=scores,
        options=options_used,
    )
    _check_noise(cal)
    return cal


def _check_population(traces: Traces, camera: Camera) -> None:
    """Refuse empty traces; warn on a z step too coarse for the depth of focus."""
    if len(traces) == 0:
        raise ValueError("No calibration particles: the traces are empty.")
    check_z_step(float(np.median(np.diff(traces.z_nm))), _depth_ratio(traces, camera))


def _astigmatism_angle(traces: Traces, shape: str | None) -> float | None:
    """The astigmatism angle (rad) where ``shape`` may need it (None, "auto", "auto_A"); None
    where it cannot be measured and no angle-free shape was asked for."""
    if shape not in (None, "auto", "auto_A"):
        return None
    try:
        return astigmatism_angle(traces["wx"], traces["wy"], traces["rho"])
    except ValueError:
        if shape is not None:
            raise
        return None


def _candidates(shape: str | None, theta: float | None) -> tuple[str, ...]:
    """The shape parameters to model: every one where none was asked for (the angle-free ones
    where the angle is unknown), else the paper's and the one asked for."""
    if shape is None:
        return SHAPES if theta is not None else PAPER_SHAPES
    return tuple(dict.fromkeys((*PAPER_SHAPES, shape)))


def _hard_failures(traces: Traces, local: LocalModels) -> dict[str, np.ndarray]:
    """Per-particle flags of outright failure: fits that failed (over a fifth of the planes
    its models use, :func:`~latentz.calibration.local.measured_run`: beyond that run the
    particle is simply out of range, as a defocused spot outgrowing the ROI is), no focus,
    crowded."""
    run = measured_run(traces, local.z_nm, local.z_f)
    converged = row_mean(np.where(run, traces["converged"], np.nan))
    return {
        "fit_failed": converged < 0.8,
        "never_in_focus": ~local.in_focus,
        "crowded": traces.crowded,
    }


def _choose_shape(
    traces: Traces,
    local: LocalModels,
    usable: np.ndarray,
    tilt: bool,
    camera: Camera,
    roi_size: int | None,
) -> tuple[str, Any]:
    """The shape parameter with the best expected σ_z, scored on the ``usable`` particles'
    levelled models, and why (:func:`latentz.calibration.shape_choice.choose`)."""
    position = traces.position()
    substrate_nm = position * camera.pixel_size_nm
    level = _tilt_plane(substrate_nm, local.z_f, usable, tilt)
    table = score_shapes(
        local.shifted(level(*substrate_nm.T)),
        traces,
        usable,
        roi_size=roi_size or _FIRST_ROI,
        readnoise=camera.readnoise,
        positions=position,
    )
    return choose(table)


def _cull(
    traces: Traces,
    local: LocalModels,
    shape: str,
    hard: dict[str, np.ndarray],
    tilt: bool,
    px: float,
    *,
    cull: bool,
    threshold: float,
    k: int,
) -> tuple[np.ndarray, np.ndarray, pd.DataFrame, TiltPlane]:
    """Culled flags, their reasons, the culling scores and the focal plane of the kept
    particles: outright failures (``hard``), and outliers of the population where there is
    one (at least :data:`_MIN_POPULATION` usable particles) and ``cull`` is on."""
    substrate_nm = traces.position() * px
    failed = np.any(np.stack(list(hard.values())), axis=0)
    plane = _tilt_plane(substrate_nm, local.z_f, ~failed, tilt)
    scores = pd.DataFrame(index=np.arange(len(traces)))
    if not (cull and np.count_nonzero(~failed) >= _MIN_POPULATION):
        return failed, _reasons(hard), scores, plane
    shifted = local.shifted(plane(*substrate_nm.T))
    features = particle_features(traces, shifted, shape, substrate_nm, ~failed, k=k)
    culled, reason, scores = cull_particles(features, hard, threshold=threshold)
    return culled, reason, scores, _tilt_plane(substrate_nm, local.z_f, ~culled, tilt)


#: ``noise_scale`` below which :func:`calibrate` warns: the images' variance under half the
#: camera model's.
NOISE_WARNING_SCALE = 1 / np.sqrt(2)


def _check_noise(cal: Calibration) -> None:
    """Say so when the calibration images scatter much less than the camera's gain implies
    (:attr:`Calibration.noise_scale`)."""
    scale, gain = cal.noise_scale, cal.camera.gain
    if scale < NOISE_WARNING_SCALE:
        warn(
            f"The calibration images scatter in z {scale:.2f}x as much as gain {gain:.3g} e-/ADU "
            f"predicts: the frames were averaged, or the gain is too low (the images behave as "
            f"if it were at least {gain / scale**2:.2g} e-/ADU); z errors are scaled by "
            f"{scale:.2f}. Give that effective gain (--gain, or Camera(gain=...)) to use it."
        )


def _check_offset(camera: Camera, stacks: list[np.ndarray]) -> None:
    """Refuse a camera offset (ADU) above the median of the calibration images: most pixels
    would hold negative photons and no particle would be found."""
    sample = np.concatenate([np.ravel(st[:: max(1, len(st) // 8), ::2, ::2]) for st in stacks])
    median = float(np.median(sample))
    if camera.offset > median:
        raise ValueError(
            f"The camera offset {camera.offset:g} ADU is above the median {median:g} ADU of the "
            "calibration images: give the camera's real offset (below that), or leave it out "
            "to estimate it."
        )


def _reasons(flags: dict[str, np.ndarray]) -> np.ndarray:
    """Comma-separated names of the flags each particle carries."""
    n = len(next(iter(flags.values())))
    return np.array([",".join(k for k, m in flags.items() if m[i]) for i in range(n)], object)


def _check_kept(culled: np.ndarray, reason: np.ndarray, roi_size: int | None) -> None:
    """One clear error when every calibration particle failed, naming the reasons."""
    if not culled.all():
        return
    counts = pd.Series([r for rs in reason for r in str(rs).split(",") if r]).value_counts()
    listed = ", ".join(f"{k}: {v}" for k, v in counts.items())
    hint = "roi_size=None (or a larger ROI)" if "fit_failed" in counts else "the inputs"
    raise ValueError(
        f"Every one of the {culled.size} calibration particles failed ({listed}); "
        f"check {hint}, the camera and the z positions."
        + (f" The ROI was {roi_size} px." if roi_size else "")
    )


def _field_model_for(field_model: str, n_kept: int) -> str:
    """``field_model``, or "nearest" (with one line saying so) when too few particles are
    kept to carry models across the field."""
    if field_model != "nearest" and n_kept < _MIN_WIDEFIELD:
        warn(
            f"{n_kept} calibration particle(s) kept: field_model={field_model!r} needs at least "
            f"{_MIN_WIDEFIELD}, so the nearest particle's models are used (field_model='nearest')."
        )
        return "nearest"
    return field_model


def _depth_ratio(traces: Traces, camera: Camera) -> float:
    """Depth of focus over squared in-focus width of the converged spot widths, x and y of each
    particle (:func:`latentz.calibration.depth.depth_ratio_per_nm`), nm⁻¹."""
    converged = traces["converged"]
    widths = [np.where(converged, traces[w], np.nan) * camera.pixel_size_nm for w in ("wx", "wy")]
    return depth_ratio_per_nm(traces.z_nm, np.stack(widths, axis=1).reshape(-1, traces.z_nm.size))


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

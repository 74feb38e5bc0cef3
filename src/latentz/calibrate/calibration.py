"""Through-focus calibration and 3D localization with it (METHOD.md items 5–13, 16–18, 21).

:func:`calibrate` turns through-focus stacks of calibration particles into a :class:`Calibration`:
traces of every particle, its local models (z_f, Δx'(z), Δy'(z), z(shape) with σ's), culling of
defective particles, and removal of the substrate tilt so that z = 0 is the focal surface of the
calibration particles after levelling. :meth:`Calibration.apply` localizes spots in 3D with the
local models of the nearest calibration particle (``field_model="nearest"``). The widefield models
("zernike", "natural") are integrated in a later stage.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.validate import (
    check_array,
    check_choice,
    check_columns,
    check_int,
    check_positive,
)
from latentz.calibrate.culling import cull as cull_particles
from latentz.calibrate.culling import particle_features
from latentz.calibrate.local import LocalModels, LocalOptions, fit_local, row_mean
from latentz.calibrate.shape import (
    SHAPES,
    astigmatism_angle,
    shape_sigma,
    shape_value,
    uses_amplitude,
)
from latentz.calibrate.tilt import TiltPlane
from latentz.calibrate.traces import Traces, extract_traces
from latentz.camera import Camera

__all__ = ["Calibration", "calibrate", "calibrate_traces", "FIELD_MODELS", "PAPER_SHAPES"]

FIELD_MODELS = ("zernike", "natural", "nearest")
PAPER_SHAPES = ("rho", "rho_w", "rho_A")
SPOT_COLUMNS = ("x", "y", "amplitude", "wx", "wy", "rho")
_ERROR_COLUMNS = ("wx_err", "wy_err", "rho_err", "amplitude_err")
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
        How models are carried across the field. Only "nearest" is available in this version.
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
    **options
        ``tilt`` (bool, default True): fit and remove the substrate tilt;
        ``cull`` (bool, default True) and ``cull_threshold`` (robust z-score, default 6),
        ``neighbours`` (default 8) — with fewer than 10 usable particles only outright failures
        are culled, as population statistics need a population; and the
        :class:`~latentz.calibrate.local.LocalOptions` fields (``amplitude_order``,
        ``focus_fraction``, ``lateral_order``, ``shape_order``,
        ``sigma_window_nm``, ``min_range_nm``).

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        Too few planes for the polynomial orders, non-monotonic ``z_nm``, or no particles.
    NotImplementedError
        ``field_model`` other than "nearest" (the widefield stage is not integrated yet).
    """
    camera = Camera() if camera is None else camera
    if not isinstance(camera, Camera):
        raise TypeError(f"Expected `camera` to be a latentz Camera, got {type(camera).__name__}.")
    local_options = _local_options(dict(options))
    z = _check_z(z_nm, local_options)
    check_choice("shape", shape, SHAPES)
    check_choice("field_model", field_model, FIELD_MODELS)
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
    )
    return calibrate_traces(
        traces, camera=camera, shape=shape, field_model=field_model, n_terms=n_terms, **options
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
    if field_model != "nearest":
        raise NotImplementedError(
            f"field_model={field_model!r} needs the widefield calibration stage, which is not "
            "integrated in this version; use field_model='nearest'."
        )
    if len(traces) == 0:
        raise ValueError("No calibration particles: the traces are empty.")
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


def _tilt_plane(substrate_nm: np.ndarray, z_f: np.ndarray, use: np.ndarray, tilt: bool):
    """Plane of best focus over the usable particles; a flat plane at their mean z_f when the
    tilt is not wanted or cannot be determined (fewer than 3 particles, or collinear ones)."""
    use = use & np.isfinite(z_f)
    if not use.any():
        use = np.isfinite(z_f)
    z0 = float(np.mean(z_f[use])) if use.any() else 0.0
    if not tilt:
        return TiltPlane.flat(z0)
    try:
        return TiltPlane.from_estimate(*substrate_nm.T, z_f, mask=use)
    except ValueError:
        return TiltPlane.flat(z0)


@dataclass(frozen=True, eq=False)
class Calibration:
    """A through-focus calibration: local models of every calibration particle.

    Build it with :func:`calibrate`. All z values are on the tilt-corrected axis (nm): z = 0 is the
    plane of best focus of the calibration particles, so ``particles.z_f_nm`` is the field
    curvature. Positions ``x``, ``y`` are camera pixels.

    Attributes
    ----------
    camera : Camera
    traces : Traces
        Per-plane fit results of the calibration particles.
    local : LocalModels
        Local models on the tilt-corrected axis.
    plane : TiltPlane
        Plane of best focus over the substrate (piezo z, nm).
    culled, reason : ndarray (n,)
        Culling flags and reasons.
    scores : DataFrame
        Robust z-scores of the culling features.
    options : dict
        Every option used.
    """

    camera: Camera
    traces: Traces
    local: LocalModels
    plane: TiltPlane
    culled: np.ndarray
    reason: np.ndarray
    scores: pd.DataFrame
    options: dict[str, Any]
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> str:
        """The shape parameter used for axial localization."""
        return self.options["shape"]

    @property
    def tilt_mrad(self) -> float:
        """Nutation of the substrate normal from the optical axis, mrad."""
        return self.plane.nutation_mrad

    @property
    def positions(self) -> np.ndarray:
        """(x, y) camera position of every calibration particle, pixels, shape (n, 2)."""
        if "positions" not in self._cache:
            self._cache["positions"] = self.traces.position()
        return self._cache["positions"]

    @property
    def kept(self) -> np.ndarray:
        """Indices of the calibration particles that were not culled."""
        return np.flatnonzero(~self.culled)

    @property
    def particles(self) -> pd.DataFrame:
        """One row per calibration particle (see the module docs for the columns)."""
        if "particles" not in self._cache:
            self._cache["particles"] = _particle_table(self)
        return self._cache["particles"].copy()

    def mean_sigma_z(self, shape: str, range_nm: float, *, coverage: float = 0.9) -> np.ndarray:
        """Mean σ_z (nm) of each particle over ``|z − z_f| ≤ range_nm / 2`` (Fig. 3's overbar).

        NaN for a particle whose monotonic range covers less than ``coverage`` of those planes.
        """
        model = self.local.shapes[shape]
        near = np.abs(self.local.z_nm - self.local.z_f[:, None]) <= range_nm / 2
        have = near & np.isfinite(model.sigma_z)
        frac = have.sum(axis=1) / np.maximum(near.sum(axis=1), 1)
        mean = row_mean(np.where(have, model.sigma_z, np.nan))
        return np.where(frac >= coverage, mean, np.nan)

    def local_z(self, value: Any, *, shape: str | None = None) -> np.ndarray:
        """z (nm) of every calibration particle for one shape value (scalar or (n,) array).

        NaN where the value is outside the particle's monotonic range (never extrapolated).
        """
        model = self.local.shapes[shape or self.shape].inverse
        s = np.broadcast_to(np.asarray(value, dtype=np.float64), (len(model),))
        z = model(s)
        return np.where(model.contains(s) & model.valid, z, np.nan)

    def local_delta(self, z_nm: Any) -> tuple[np.ndarray, np.ndarray]:
        """Δx'(z), Δy'(z) (pixels) of every calibration particle at z (scalar or (n,) array)."""
        z = np.broadcast_to(np.asarray(z_nm, dtype=np.float64), (len(self.local.dx),))
        return self.local.dx(z), self.local.dy(z)

    def nearest(self, x: Any, y: Any) -> np.ndarray:
        """Index of the nearest kept calibration particle to each (x, y) camera position."""
        if "tree" not in self._cache:
            if self.kept.size == 0:
                raise ValueError("Every calibration particle was culled: nothing to apply.")
            self._cache["tree"] = cKDTree(self.positions[self.kept])
        _, idx = self._cache["tree"].query(np.column_stack([x, y]))
        return self.kept[idx]

    def apply(
        self, spots: pd.DataFrame, *, amplitude_reference: str = "calibration"
    ) -> pd.DataFrame:
        """Localize spots in 3D (nearest calibration particle's local models).

        Parameters
        ----------
        spots : DataFrame
            From ``localize`` / ``fit_rois``: x, y (camera pixels), amplitude, wx, wy, rho, and
            optionally their ``*_err`` columns (then errors are propagated per spot).
        amplitude_reference : {"calibration", "particle"}
            For A-normalised shapes ("rho_A", "auto_A"): A_{ρ=ρ0} of the nearest calibration
            particle (emitters as bright as the calibration particles), or of each emitter's own
            track (the spot with the smallest |ρ| in its ``particle`` group).

        Returns
        -------
        DataFrame
            A copy of ``spots`` with x_nm, y_nm, z_nm, x_err_nm, y_err_nm, z_err_nm, in_range and
            cal_particle (index of the calibration particle used). Outside that particle's
            calibrated range, z_nm and the corrected positions are NaN and in_range is False.
        """
        check_columns("spots", spots, SPOT_COLUMNS)
        check_choice("amplitude_reference", amplitude_reference, ("calibration", "particle"))
        shape = self.shape
        cols = {c: spots[c].to_numpy(dtype=np.float64) for c in SPOT_COLUMNS}
        located = np.isfinite(cols["x"]) & np.isfinite(cols["y"])
        p = self.nearest(np.where(located, cols["x"], 0.0), np.where(located, cols["y"], 0.0))
        model = self.local.shapes[shape]
        theta = self.local.theta
        ref = model.amplitude_ref[p]
        if uses_amplitude(shape) and amplitude_reference == "particle":
            check_columns("spots", spots, ("particle",))
            ref = _track_reference(shape, spots, cols, theta)
        s = shape_value(
            shape,
            cols["wx"],
            cols["wy"],
            cols["rho"],
            cols["amplitude"],
            theta=theta,
            amplitude_ref=ref,
        )
        inverse = model.inverse[p]
        in_range = inverse.contains(s) & inverse.valid & np.isfinite(s) & located
        z = np.where(in_range, inverse(np.where(in_range, s, 0.0)), np.nan)
        sigma_cal = _interp_rows(self.local.z_nm[p], model.sigma_z[p], z)
        m_used = np.sum(np.isfinite(model.sigma_z[p]), axis=1)
        model_part = sigma_cal * np.sqrt((inverse.order + 1) / np.maximum(m_used, 1))
        if all(c in spots.columns for c in _ERROR_COLUMNS):
            errs = tuple(spots[c].to_numpy(dtype=np.float64) for c in _ERROR_COLUMNS)
            sigma_s = shape_sigma(
                shape,
                cols["wx"],
                cols["wy"],
                cols["rho"],
                cols["amplitude"],
                errs,
                theta=theta,
                amplitude_ref=ref,
            )
            slope = inverse.derivative()(np.where(in_range, s, 0.0))
            z_err = np.hypot(slope * sigma_s, model_part)
        else:
            z_err = sigma_cal
        px = self.camera.pixel_size_nm
        out = spots.copy()
        zq = np.where(in_range, z, 0.0)
        for axis, delta, sig in (
            ("x", self.local.dx, self.local.sigma_dx),
            ("y", self.local.dy, self.local.sigma_dy),
        ):
            sub = delta[p]
            shift = sub(zq)
            slope = sub.derivative()(zq)
            sigma_d = _interp_rows(self.local.z_nm[p], sig[p], z)
            m_d = np.sum(np.isfinite(sig[p]), axis=1)
            model_d = sigma_d * np.sqrt((sub.order + 1) / np.maximum(m_d, 1))
            own = spots[f"{axis}_err"].to_numpy(float) if f"{axis}_err" in spots else sigma_d
            err = np.sqrt(own**2 + model_d**2 + (slope * z_err) ** 2)
            out[f"{axis}_nm"] = np.where(in_range, (cols[axis] - shift) * px, np.nan)
            out[f"{axis}_err_nm"] = np.where(in_range, err * px, np.nan)
        out["z_nm"] = z
        out["z_err_nm"] = np.where(in_range, z_err, np.nan)
        out["in_range"] = in_range
        out["cal_particle"] = p
        return out


def _track_reference(shape: str, spots: pd.DataFrame, cols: dict, theta) -> np.ndarray:
    """A_{ρ=ρ0} of each spot's own track: the amplitude of its spot with the smallest |ρ|
    (or |e_θ| for "auto_A")."""
    base = np.abs(
        shape_value(
            "rho" if shape == "rho_A" else "auto", cols["wx"], cols["wy"], cols["rho"], theta=theta
        )
    )
    if shape == "auto_A":
        base = base / ((np.abs(cols["wx"]) + np.abs(cols["wy"])) / 2)
    frame = pd.DataFrame(
        {"track": spots["particle"].to_numpy(), "base": base, "amplitude": cols["amplitude"]}
    )
    best = frame.loc[frame.groupby("track")["base"].idxmin(), ["track", "amplitude"]]
    lookup = dict(zip(best["track"], best["amplitude"], strict=True))
    return frame["track"].map(lookup).to_numpy(dtype=np.float64)


def _interp_rows(z_grid: np.ndarray, values: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values[i]`` (on ``z_grid[i]``) at ``z[i]``, row by row; NaN
    values are bridged by their nearest finite neighbour."""
    filled = pd.DataFrame(values.T).ffill().bfill().to_numpy().T
    n, n_z = z_grid.shape
    rows = np.arange(n)
    j = np.clip(np.sum(z_grid < np.where(np.isfinite(z), z, -np.inf)[:, None], axis=1), 1, n_z - 1)
    z0, z1 = z_grid[rows, j - 1], z_grid[rows, j]
    w = np.clip((z - z0) / (z1 - z0), 0.0, 1.0)
    return (1 - w) * filled[rows, j - 1] + w * filled[rows, j]


def _particle_table(cal: Calibration) -> pd.DataFrame:
    local, traces = cal.local, cal.traces
    px = cal.camera.pixel_size_nm
    pos = cal.positions
    table = pd.DataFrame(
        {
            "particle": np.arange(len(traces)),
            "stack": traces.stack,
            "x": pos[:, 0],
            "y": pos[:, 1],
            "x_nm": pos[:, 0] * px,
            "y_nm": pos[:, 1] * px,
            "z_f": local.z_f + cal.plane(*(pos * px).T),
            "z_f_nm": local.z_f,
            "in_focus": local.in_focus,
        }
    )
    for name, model in local.shapes.items():
        table[f"sigma_z_{name}"] = row_mean(model.sigma_z)
        table[f"z_min_{name}"] = model.z_range[:, 0]
        table[f"z_max_{name}"] = model.z_range[:, 1]
    table["sigma_z"] = table[f"sigma_z_{cal.shape}"]
    table["z_min_nm"] = table[f"z_min_{cal.shape}"]
    table["z_max_nm"] = table[f"z_max_{cal.shape}"]
    table["sigma_dx_nm"] = row_mean(local.sigma_dx) * px
    table["sigma_dy_nm"] = row_mean(local.sigma_dy) * px
    table["culled"] = cal.culled
    table["cull_reason"] = cal.reason
    table["reason"] = cal.reason
    for column in cal.scores.columns:
        table[f"score_{column}"] = cal.scores[column].to_numpy()
    model = local.shapes[cal.shape].inverse
    table["z_coef"] = list(model.coef)
    table["z_domain"] = list(model.domain)
    table["dx_coef"] = list(local.dx.coef)
    table["dy_coef"] = list(local.dy.coef)
    table["lateral_domain_nm"] = list(local.dx.domain)
    table["amplitude_coef"] = list(local.amplitude.coef)
    return table

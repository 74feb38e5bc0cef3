"""The result of calibration, and 3D localization with it (paper Fig. 4, Supp. Table 2).

A :class:`Calibration` holds the traces and local models of every calibration particle on the
tilt-corrected z axis (z = 0 is the focal surface of the calibration particles after levelling)
and the widefield models built from them. :meth:`Calibration.apply` localizes spots in 3D: z from
the field model of z at the spot's shape value (or, with ``z_readout="joint"``, the value whose
z its fitted wx, wy, ρ fit best jointly, :mod:`latentz.calibration.readout`), then the lateral
correction at that z; shape values outside what the particles cover are flagged, never
extrapolated.
:meth:`Calibration.local_z` and :meth:`Calibration.local_delta` evaluate every particle's models
at once, for the widefield models. The file layout is described in docs/file-format.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.columns import with_columns
from latentz._shared.sanity import check_roi_size, check_widths
from latentz._shared.validate import check_choice, check_columns
from latentz.calibration.dimming import background_ratio
from latentz.calibration.errors import (
    DEPTH_FRACTION,
    ONE_SIGMA,
    FieldLine,
    combine,
    field_line,
    reference_sigma,
    spread_through,
)
from latentz.calibration.fieldmodels import FIELD_MODEL_KINDS
from latentz.calibration.local import LocalModels, focus_depth_nm, row_mean
from latentz.calibration.local_errors import error_model, lack_of_fit, model_sigma
from latentz.calibration.noise_scale import (
    calibration_scatter,
    fit_part_z,
    noise_scale,
    noise_scale_at,
    noise_scale_by_z,
    through_inverse,
)
from latentz.calibration.particle_curves import curves_at, usable_scatter
from latentz.calibration.particle_table import particle_table
from latentz.calibration.readout import (
    SHAPE_PARAMS,
    JointZ,
    joint_z,
    profile_width,
    shape_covariance,
)
from latentz.calibration.reference import ReferenceField
from latentz.calibration.rows import interp_rows, row_weights
from latentz.calibration.shape import shape_value, uses_amplitude
from latentz.calibration.spot_columns import (
    ERROR_COLUMNS,
    PARAMS,
    SPOT_COLUMNS,
    spot_arrays,
    stacked,
)
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import Traces
from latentz.camera import Camera
from latentz.fit.api import CORRELATION_COLUMNS

__all__ = ["Calibration", "FIELD_CHOICES", "FIELD_MODELS", "PAPER_SHAPES"]

FIELD_MODELS = FIELD_MODEL_KINDS
#: What ``field_model`` accepts: a model, or "auto" (the best by cross-validation).
FIELD_CHOICES = (*FIELD_MODELS, "auto")
PAPER_SHAPES = ("rho", "rho_w", "rho_A")
#: How :meth:`Calibration.apply` reads z from a spot's shape.
Z_READOUTS = ("joint", "shape")
#: A spot whose mean width is more than this many times its particle's curves at its z lies
#: beyond the particle's monotonic range: there the shape value returns to values inside the
#: range while the widths keep growing. The quality verdict's χ² (10 % curve scatter, limit
#: 200) calls such a spot inconsistent too, so single molecules lose nothing more to it.
BEYOND_WIDTH = 2.0
#: Spots searched at once against every plane at their own brightness (:meth:`_past_turn`):
#: the refits read take about 47 values per spot and plane, 19 MB for 200 planes.
_PLANE_CHUNK = 256


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
    provenance : dict
        Where it came from: the inputs' names and SHA-256, the latentz version and the date
        (filled by :meth:`save`, the CLI, and read back by :meth:`load`).
    """

    camera: Camera
    traces: Traces
    local: LocalModels
    plane: TiltPlane
    culled: np.ndarray
    reason: np.ndarray
    scores: pd.DataFrame
    options: dict[str, Any]
    provenance: dict[str, Any] = field(default_factory=dict)
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    def as_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The whole state as ``({"group/name": ndarray}, JSON-able attributes)``."""
        from latentz.calibration.storage import to_arrays

        return to_arrays(self)

    def save(self, path: Any, *, provenance: dict[str, Any] | None = None) -> None:
        """Write to an HDF5 file atomically; :meth:`load` reads it back exactly.

        ``provenance`` (JSON-able, e.g. input files and their SHA-256) is added to
        :attr:`provenance` and stored with the options, camera, the latentz version and the date.
        """
        from latentz.calibration.storage import save

        save(self, path, provenance=provenance)

    @classmethod
    def load(cls, path: Any) -> Calibration:
        """Read a calibration written by :meth:`save`."""
        from latentz.calibration.storage import load

        return load(path, factory=cls)

    @property
    def shape(self) -> str:
        """The shape parameter used for axial localization."""
        return self.options["shape"]

    @property
    def roi_size(self) -> int:
        """Side of the ROI the calibration spots were fitted in, pixels: spots to localize with
        this calibration must be fitted in the same ROI (their widths depend on it)."""
        return int(self.options.get("roi_size") or 15)

    @property
    def method(self) -> str:
        """The fit method of the calibration spots ("mle", "wlsq" or "lsq")."""
        return self.options.get("method", "mle")

    @property
    def shape_choice(self) -> dict[str, Any] | None:
        """Why the shape parameter was picked (``calibrate(shape=None)``): ``chosen``, a one-line
        ``reason`` and each candidate's ``scores``; None when the user gave the shape."""
        return self.options.get("shape_choice")

    @property
    def usable_planes(self) -> np.ndarray:
        """(n, n_z) mask of each particle's planes where a 1000-photon emitter's Cramér–Rao σ_z
        stays near its best (:func:`~latentz.calibration.precision.usable_planes`): beyond them
        the PSF hardly changes with z (far defocus, ring images)."""
        if "usable_planes" not in self._cache:
            from latentz.calibration.precision import (
                REFERENCE_PHOTONS,
                crlb_sigma_z,
                usable_planes,
            )

            sigma = crlb_sigma_z(
                self.local,
                self.traces,
                self.shape,
                REFERENCE_PHOTONS,
                roi_size=self.roi_size,
                readnoise=self.camera.readnoise,
            )
            self._cache["usable_planes"] = usable_planes(sigma)
        return self._cache["usable_planes"]

    @property
    def usable_z_nm(self) -> np.ndarray:
        """(n, 2) lowest and highest tilt-corrected z (nm) of each particle's usable planes
        (NaN where none): spots localized outside it are not `good`."""
        if "usable_z" not in self._cache:
            z = np.where(self.usable_planes, self.local.z_nm, np.nan)
            with np.errstate(invalid="ignore"):
                import warnings

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    span = np.stack([np.nanmin(z, axis=1), np.nanmax(z, axis=1)], axis=1)
            self._cache["usable_z"] = span
        return self._cache["usable_z"]

    def curves_at(self, particle: Any, z_nm: Any) -> dict[str, np.ndarray]:
        """The calibration curves wx, wy (px) and ρ of particles ``particle`` at tilt-corrected
        ``z_nm`` (arrays of one shape), from their traces smoothed by a running median of 5
        planes; ``<name>_scatter``: each particle's RMS scatter of the trace about that curve."""
        return curves_at(self, particle, z_nm)

    def shapes_at_particle_brightness(self, located: pd.DataFrame) -> np.ndarray | None:
        """(n, 3) fitted wx, wy (px) and ρ of spots that :meth:`apply` located (their
        ``cal_particle`` and ``z_nm``) less the brightness shift its dimmed refits measure
        (:meth:`_shape_params_shift`): the shapes their particle's own fit would show at their
        z, comparable with :meth:`curves_at`; None where the calibration has no dimmed refits
        or the spots no ``background``."""
        cols = {c: located[c].to_numpy(float) for c in ("amplitude", "background")
                if c in located.columns}  # fmt: skip
        shift = self._shape_params_shift(cols, located["cal_particle"].to_numpy(int),
                                         located["z_nm"].to_numpy(float))  # fmt: skip
        return None if shift is None else located[list(SHAPE_PARAMS)].to_numpy(float) - shift

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
    def field_model(self) -> str:
        """How models are carried across the field: "zernike", "natural", "curves" or "nearest".

        For ``field_model="auto"`` the one chosen by cross-validation
        (:func:`~latentz.calibration.crossval.choose_field_model`) on first use; with fewer than
        :data:`~latentz.calibration.crossval.MIN_FIELD_PARTICLES` kept particles, "nearest"
        (with a warning).
        """
        asked = self.options.get("field_model", "nearest")
        if asked != "auto":
            return asked
        if "chosen_field_model" not in self._cache:
            from latentz.calibration.crossval import resolve_auto

            self._cache["chosen_field_model"] = resolve_auto(self)
        return self._cache["chosen_field_model"]

    @property
    def crossval(self) -> pd.DataFrame:
        """Held-out errors of every field model (:func:`~latentz.calibration.crossval.crossval`),
        computed on first use and stored in the calibration file."""
        return pd.concat([self.crossval_of(kind) for kind in FIELD_MODELS], ignore_index=True)

    def crossval_of(self, kind: str) -> pd.DataFrame:
        """The rows of :attr:`crossval` for one field model (computed alone when needed)."""
        key = f"crossval/{check_choice('kind', kind, FIELD_MODELS)}"
        if key not in self._cache:
            from latentz.calibration.crossval import crossval

            self._cache[key] = crossval(self, (kind,))
        return self._cache[key]

    @property
    def widefield(self):
        """The widefield models of the kept particles, built on first use from the local models
        (so a saved and loaded calibration gives the same model): the particles' own curves
        (:class:`~latentz.calibration.widefield.CurveModel`) for ``field_model="curves"``, or
        tabulated (:class:`~latentz.calibration.widefield.WidefieldModel`); None for
        ``field_model="nearest"``."""
        if self.field_model == "nearest":
            return None
        if "widefield" not in self._cache:
            from latentz.calibration.widefield import CurveModel, WidefieldModel

            if self.field_model == "curves":
                self._cache["widefield"] = CurveModel.from_calibration(
                    self, field_shape=tuple(self.options["field_shape"])
                )
                return self._cache["widefield"]
            self._cache["widefield"] = WidefieldModel.from_calibration(
                self,
                kind=self.field_model,
                field_shape=tuple(self.options["field_shape"]),
                n_terms=self.options.get("n_terms", 400),
            )
        return self._cache["widefield"]

    def evaluate(self, **options: Any) -> pd.DataFrame:
        """Widefield errors against z for each field model (paper Fig. 5); see
        :func:`latentz.calibration.evaluate.evaluate`."""
        from latentz.calibration.evaluate import evaluate

        return evaluate(self, **options)

    def evaluate_figures(self, **options: Any) -> dict[str, Any]:
        """Figs. 4 and 5 as matplotlib figures, by name; see
        :func:`latentz.calibration.evaluate.evaluate_figures`."""
        from latentz.calibration.evaluate import evaluate_figures

        return evaluate_figures(self, **options)

    @property
    def width_range_px(self) -> tuple[float, float]:
        """Smallest and largest fitted width (wx, wy, pixels) of the kept particles' traces."""
        if self.kept.size == 0:
            raise ValueError(
                f"This calibration kept none of its {len(self.culled)} particles (see "
                "cal.particles['reason']), so it cannot localize: recalibrate with more "
                "particles or a ROI that holds them."
            )
        widths = np.stack([self.traces["wx"][self.kept], self.traces["wy"][self.kept]])
        return float(np.nanmin(widths)), float(np.nanmax(widths))

    @property
    def kept(self) -> np.ndarray:
        """Indices of the calibration particles that were not culled."""
        return np.flatnonzero(~self.culled)

    @property
    def heights_nm(self) -> np.ndarray:
        """Each particle's own height (nm) taken off its models; zeros where none was."""
        heights = self.options.get("particle_heights", {}).get("heights_nm")
        return np.zeros(len(self.traces)) if heights is None else np.asarray(heights, float)

    @property
    def particles(self) -> pd.DataFrame:
        """One row per calibration particle.

        Columns: ``particle``, ``stack``; ``x``, ``y`` (field pixels) and ``x_nm``, ``y_nm``;
        ``z_f`` (piezo z of best focus, nm), ``height_nm`` (the particle's own height taken off
        its models, :mod:`latentz.calibration.heights`) and ``z_f_nm`` (after tilt and height
        removal: the field curvature); ``in_focus``; for each modelled shape s,
        ``sigma_z_<s>`` (mean σ_z over its monotonic range, nm) and ``z_min_<s>``,
        ``z_max_<s>`` (that range, tilt-corrected nm);
        ``sigma_z``, ``z_min_nm``, ``z_max_nm`` for the calibration's shape; ``sigma_dx_nm``,
        ``sigma_dy_nm``; ``culled``, ``cull_reason`` (= ``reason``) and the culling scores
        ``score_<feature>``; and the polynomial coefficients (Chebyshev, scaled domain):
        ``z_coef``/``z_domain`` of z(shape), ``dx_coef``, ``dy_coef``/``lateral_domain_nm``,
        ``amplitude_coef``.
        """
        if "particles" not in self._cache:
            self._cache["particles"] = particle_table(self)
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

    @property
    def z_span_nm(self) -> np.ndarray:
        """(n, 2) lowest and highest tilt-corrected z (nm) of the planes each particle's local
        models were fitted to (its measured run about focus, :func:`~latentz.calibration.local.
        fit_local`): the only z over which they are known. Beyond a gap of failed fits an
        order-16 polynomial is unconstrained, however far the stack reaches."""
        if "z_span" not in self._cache:
            z = self.local.z_nm
            lo = np.fmax.reduce([np.nanmin(z, axis=1), self.local.dx.domain[:, 0],
                                 self.local.dy.domain[:, 0]])  # fmt: skip
            hi = np.fmin.reduce([np.nanmax(z, axis=1), self.local.dx.domain[:, 1],
                                 self.local.dy.domain[:, 1]])  # fmt: skip
            self._cache["z_span"] = np.stack([lo, hi], axis=1)
        return self._cache["z_span"]

    def in_range_window(self, p: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(n, 2) the z (nm) where a spot placed at ``z`` by particle ``p`` can lie when in
        range: p's monotonic range (widened to ``z``, which a field model may place a little
        beyond it), within the span p was imaged over (:attr:`z_span_nm`)."""
        z_range, span = self.local.shapes[self.shape].z_range[p], self.z_span_nm[p]
        lo = np.fmax(np.fmin(z_range[:, 0], z), span[:, 0])
        hi = np.fmin(np.fmax(z_range[:, 1], z), span[:, 1])
        return np.stack([lo, hi], axis=1)

    def _within_span(self, z: np.ndarray) -> np.ndarray:
        lo, hi = self.z_span_nm.T
        with np.errstate(invalid="ignore"):
            return (z >= lo) & (z <= hi)

    def local_z(self, value: Any, *, shape: str | None = None) -> np.ndarray:
        """z (nm) of every calibration particle for one shape value (scalar or (n,) array);
        NaN as in :meth:`inverse_z`."""
        n = len(self.local.z_f)
        s = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,))
        return self.inverse_z(s, np.arange(n), shape=shape)

    def inverse_z(self, s: np.ndarray, p: np.ndarray, *, shape: str | None = None) -> np.ndarray:
        """z (nm) of shape values ``s`` (m,) by particles ``p``' (m,) inverse models z(s).

        NaN where s lies outside the shape range the inverse covers, or where the inverse
        polynomial leaves the particle's monotonic z range, the planes it was fitted to (an
        order-16 z(s) overshoots between its data by microns where its slope is steep).
        """
        model = self.local.shapes[shape or self.shape]
        inverse = model.inverse[p]
        ok = inverse.contains(s) & inverse.valid & np.isfinite(s)
        z = inverse(np.where(ok, s, 0.0))
        lo, hi = model.z_range[p].T
        with np.errstate(invalid="ignore"):
            ok &= (z >= lo) & (z <= hi)
        return np.where(ok, z, np.nan)

    def local_delta(self, z_nm: Any) -> tuple[np.ndarray, np.ndarray]:
        """Δx'(z), Δy'(z) (pixels) of every calibration particle at z (scalar or (n,) array).

        NaN where z is outside the span the particle was imaged over: a polynomial of order 16
        extrapolated beyond its data is meaningless (never extrapolated).
        """
        z = np.broadcast_to(np.asarray(z_nm, dtype=np.float64), (len(self.local.dx),))
        inside = self._within_span(z)
        return (
            np.where(inside, self.local.dx(z), np.nan),
            np.where(inside, self.local.dy(z), np.nan),
        )

    @property
    def noise_scale(self) -> float:
        """Factor (≤ 1) on the fit's part of ``z_err_nm`` over all z: the kept particles'
        usable calibration images against their own fit errors (:func:`~latentz.calibration.
        errors.measured_noise`); 1 for traces without fit errors. Where it is below 1,
        :meth:`apply` uses its value about each z (:attr:`noise_scale_by_z`)."""
        return noise_scale(self)

    @property
    def noise_scale_by_z(self) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`noise_scale` about each z: tilt-corrected z (nm, ascending) and the factor
        (≤ 1) there, from every image the kept particles' inverses were fitted to, each
        residual over its fit's part and corrected for its leverage
        (:func:`~latentz.calibration.errors.noise_by_z`). Empty where :attr:`noise_scale` is 1
        (the images scatter as their fits say) or the images are too few to follow z."""
        return noise_scale_by_z(self)

    def _field_sigma(self, axis: str, z: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """The field model's 1σ (nm) on ``axis`` (:func:`~latentz.calibration.errors.
        field_sigma`), less the local models' part of the held-out errors and, laterally, the
        held-out particles' own z noise carried through Δ (:meth:`_carried_noise`)."""
        kind = self.field_model
        line = self._held_out_line(lambda: self.crossval_of(kind), kind, axis,
                                   f"crossval_line/{kind}/{axis}")  # fmt: skip
        return line.sigma(z, distance)

    def reference_sigma_nm(self, axis: str) -> float:
        """1σ (nm) of the particles' lateral reference on ``axis`` ("x" or "y"): the RMS of
        the kept particles' Δx'(z) or Δy'(z) off their plane across the field within the depth
        of focus about each z_f (:func:`~latentz.calibration.errors.reference_sigma`; the depth
        is the median over the kept particles of :func:`~latentz.calibration.local.
        focus_depth_nm` at :data:`~latentz.calibration.errors.DEPTH_FRACTION`)."""
        key = f"reference_sigma/{axis}"
        if key not in self._cache:
            kept, sigma = self.kept, 0.0
            if kept.size:
                depth = focus_depth_nm(self.local.z_nm[kept], self.traces["amplitude"][kept],
                                       DEPTH_FRACTION)  # fmt: skip
                model = (self.local.dx if axis == "x" else self.local.dy)[kept]
                z_f, span = self.local.z_f[kept], self.z_span_nm[kept]
                sigma = reference_sigma(self.positions[kept], model, z_f, span,
                                        float(np.nanmedian(depth)))  # fmt: skip
            self._cache[key] = sigma * self.camera.pixel_size_nm
        return self._cache[key]

    def _carried_noise(self, held_out: pd.DataFrame, axis: str) -> np.ndarray:
        """(rows,) nm: how far the held-out particles' own z noise moves their lateral
        ``axis`` error (:func:`~latentz.calibration.crossval.crossval` reads Δx', Δy' at the
        predicted z): the fit's part of σ_z of each held-out image (as :meth:`apply` gives a
        spot, less the smoothing crossval applies to its shape values) and its local model's
        σ (the neighbours' inverse, alike), through the particle's Δx'(z) or Δy'(z)
        (:func:`~latentz.calibration.errors.spread_through`, the width that covers 68 %, as
        for a spot). A spot's own σ_z stands for it
        (:meth:`_lateral_error`); the field's z error is not in it (a particle's height moves
        its z read and its Δ alike, and the read z's Δ holds both)."""
        from latentz.calibration.crossval import smoothed_noise

        p = held_out["particle"].to_numpy(int)
        z = held_out["z_nm"].to_numpy(float)
        fit = np.zeros(p.size)
        predicted = calibration_scatter(self)[2]
        if predicted.size and p.size:
            row = np.clip(np.searchsorted(self.kept, p), 0, self.kept.size - 1)
            plane = np.argmin(np.abs(self.local.z_nm[p] - z[:, None]), axis=1)
            fit = np.where(self.kept[row] == p, predicted[row, plane], 0.0)
            fit = np.nan_to_num(fit) * noise_scale_at(self, z) * smoothed_noise(self, p)
        noise_z = np.hypot(fit, np.nan_to_num(model_sigma(self, "z", p, z)))
        model = (self.local.dx if axis == "x" else self.local.dy)[p]
        window = self.in_range_window(p, z)
        return self.camera.pixel_size_nm * spread_through(model, z, noise_z, window,
                                                          covering=True)  # fmt: skip

    def _held_out_line(self, table: Callable[[], pd.DataFrame], kind: str, axis: str,
                       key: str, local_models: bool = True) -> FieldLine:  # fmt: skip
        """The :class:`~latentz.calibration.errors.FieldLine` of the held-out errors
        ``table()`` with the local models' σ at its rows (``local_models``; False: errors not
        read through the local models, none taken off), made once and cached under ``key``."""
        if key not in self._cache:
            held_out = table()
            scale = 1.0 if axis == "z" else self.camera.pixel_size_nm
            rows = held_out["particle"].to_numpy(int)
            model_nm = noise_nm = None
            if local_models:
                model_nm = scale * model_sigma(self, axis, rows, held_out["z_nm"].to_numpy())
                if axis != "z":
                    noise_nm = self._carried_noise(held_out, axis)
            self._cache[key] = field_line(held_out, kind, axis, model_nm=model_nm,
                                          noise_nm=noise_nm)  # fmt: skip
        return self._cache[key]

    def _pair_sigma(self, z: np.ndarray, c_spot: np.ndarray | None, distance: np.ndarray,
                    readout: str = "shape") -> np.ndarray:  # fmt: skip
        """1σ (nm) of the z error of spots at ``z`` of background ratio ``c_spot`` (None: as
        bright as the calibration) ``distance`` px from the particle that localizes them, from
        held-out particles localized by their nearer and farther neighbours with the z
        ``readout`` of :meth:`apply` (:func:`~latentz.calibration.dim_crossval.pair_table`): at
        each of its ratios c the :func:`~latentz.calibration.errors.field_sigma` line in
        distance, then linear in log c between them."""
        from latentz.calibration.dim_crossval import pair_table

        key = f"pair_table/{readout}"
        if key not in self._cache:
            self._cache[key] = pair_table(self, readout)
        table = self._cache[key]
        if len(table) == 0 or not table["in_range"].any():
            return np.zeros(np.shape(z))
        levels = np.unique(table["c"].to_numpy())
        by_level = np.array([
            self._held_out_line(lambda c=c: table[table["c"] == c], "pairs", "z",
                                f"pair_line/{readout}/{c}", readout == "shape").sigma(z, distance)
            for c in levels])  # fmt: skip
        if levels.size == 1 or c_spot is None:
            return by_level[0]
        return _interp_levels(np.log(levels), by_level, c_spot)

    def _locate(self, s: np.ndarray, p: np.ndarray, cols: dict, located: np.ndarray) -> tuple:
        """z (nm), the field models' Δx', Δy' (px; None for ``nearest``: the particle ``p``'s
        own) and in_range of shape values ``s`` at the spots' positions."""
        if self.widefield is None:
            z = np.where(located, self.inverse_z(s, p), np.nan)
            return z, None, np.isfinite(z)
        # field models of z(x', y'; s) and Δx', Δy'(x', y'; z)
        z, dx_w, dy_w, in_range = self.widefield(
            np.where(located, cols["x"], np.nan),
            np.where(located, cols["y"], np.nan),
            s,
            iterations=self.options.get("iterations", 0),
        )
        return z, {"x": dx_w, "y": dy_w}, in_range & located

    def _dimming_terms(
        self, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray, z: np.ndarray,
        plane: np.ndarray | None = None,
    ) -> tuple[Callable[[str], np.ndarray], np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """What the brightness corrections of spots of fitted ``amplitude`` and ``background``
        on particles ``p`` at ``z`` read: particle ``p``'s traces at z (``trace_at(name)``),
        the spots' background ratio c, the particle's own c there, and the c the correction
        starts from.

        Where the calibration particles' brightness follows their size (their heights were
        taken off, :mod:`latentz.calibration.heights`), spots within the calibration's own range
        of brightness at their depth (up to its dimmest particles,
        :func:`~latentz.calibration.dimming.dimmest`) are not shifted; beyond that edge the shift
        starts there, and its start moves back to the particle's own ratio c as the spot's c
        goes as far again (in log c) beyond the edge, so that dim emitters get the whole shift
        from their particle's own fit (:mod:`~latentz.calibration.dimming` notes)."""
        from latentz.calibration.dimming import dimmest

        readnoise = self.camera.readnoise
        index, stacked = self._brightness_traces()
        if plane is None:
            read = interp_rows(self.local.z_nm, stacked, p, z)  # every trace in one lookup
        else:
            read = stacked[p, plane]

        def trace_at(name: str) -> np.ndarray:
            return read[:, index[name]]

        c_spot = background_ratio(background, amplitude, readnoise)
        c_own = background_ratio(trace_at("background"), trace_at("amplitude"), readnoise)
        c_from = c_own
        if self.options.get("particle_heights", {}).get("applied"):
            if "dimmest" not in self._cache:
                rows = self.kept
                c = background_ratio(self.traces["background"][rows],
                                     self.traces["amplitude"][rows], readnoise)  # fmt: skip
                self._cache["dimmest"] = dimmest(self.local.z_nm[rows], c)
            edge = np.fmax(c_own, np.interp(z, *self._cache["dimmest"]))
            # the start fades from the edge back to the particle's own c as far again beyond it
            with np.errstate(invalid="ignore", divide="ignore"):
                c_from = np.clip(edge**2 / c_spot, c_own, edge)
        return trace_at, c_spot, c_own, c_from

    def _dimming_shift(
        self, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray, z: np.ndarray,
        ref: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        """How much brighter-than-the-spot calibration images shift the spots' shape values
        (:func:`~latentz.calibration.dimming.shape_shift`), from particle ``p``'s refits at the
        spots' z (:meth:`_dimming_terms`); 0 where that is unknown."""
        from latentz.calibration.dimming import shape_shift

        def shape_of(a, wx, wy, rho):
            return shape_value(self.shape, wx, wy, rho, a, theta=self.local.theta,
                               amplitude_ref=ref)  # fmt: skip

        shift = shape_shift(shape_of, *self._dimming_terms(amplitude, background, p, z))
        return np.where(np.isfinite(shift), shift, 0.0)

    def _position_shifts(
        self, amplitude: np.ndarray, background: np.ndarray, p: np.ndarray, z: np.ndarray
    ) -> dict[str, np.ndarray]:
        """How much brighter-than-the-spot calibration images shift the spots' fitted x and y
        (px, :func:`~latentz.calibration.dimming.position_shift`), from particle ``p``'s
        refits at the spots' z (:meth:`_dimming_terms`); 0 where that is unknown."""
        from latentz.calibration.dimming import position_shift

        shift = position_shift(*self._dimming_terms(amplitude, background, p, z))
        shift = np.where(np.isfinite(shift), shift, 0.0)
        return {"x": shift[:, 0], "y": shift[:, 1]}

    def _brightness_traces(self) -> tuple[dict[str, int], np.ndarray]:
        """The traces the brightness corrections read (the calibration's own fit and its
        refits, :data:`~latentz.calibration.dimming.DIM_COLUMNS`) stacked (n, n_z, k), so
        that one lookup reads them all, and each name's index in the last axis; computed once
        (k ≤ 47 traces: about 45 MB for 1000 particles of 121 planes)."""
        from latentz.calibration.dimming import DIM_COLUMNS

        if "brightness_traces" not in self._cache:
            names = [name for name in ("amplitude", "wx", "wy", "rho", "background", *DIM_COLUMNS)
                     if name in self.traces.data]  # fmt: skip
            stacked = np.stack([self.traces[name] for name in names], axis=2)
            self._cache["brightness_traces"] = ({n: k for k, n in enumerate(names)}, stacked)
        return self._cache["brightness_traces"]

    def _transfer_sigma(self, z: np.ndarray, c_spot: np.ndarray) -> np.ndarray:
        """1σ (nm) of the dimming correction carried from the nearest particle to spots at
        ``z`` of background ratio ``c_spot``, measured on held-out particles
        (:func:`~latentz.calibration.dim_crossval.transfer_sigma`): linear in z between its
        bins and in log c between its levels, held at the ends; 0 where unknown."""
        from latentz.calibration.dim_crossval import transfer_sigma

        if "transfer_sigma" not in self._cache:
            self._cache["transfer_sigma"] = transfer_sigma(self)
        centres, log_c, sigma = self._cache["transfer_sigma"]
        if centres.size == 0:
            return np.zeros(np.shape(z))
        zq = np.where(np.isfinite(z), z, centres[0])
        by_level = np.array([np.interp(zq, centres, row) for row in sigma])  # (levels, spots)
        return _interp_levels(log_c, by_level, c_spot)

    @property
    def reference_field(self) -> ReferenceField:
        """A-normalised shapes' reference amplitude across the field, from the kept particles
        (:class:`~latentz.calibration.reference.ReferenceField`)."""
        if "reference_field" not in self._cache:
            rows = self.kept
            ref = self.local.shapes[self.shape].amplitude_ref[rows]
            self._cache["reference_field"] = ReferenceField(self.positions[rows], ref)
        return self._cache["reference_field"]

    def _particle_references(self) -> np.ndarray:
        """(n,) :attr:`reference_field` at every particle's position (computed once), so that a
        spot takes its nearest particle's entry instead of a tree query of its own."""
        if "particle_references" not in self._cache:
            self._cache["particle_references"] = self.reference_field(*self.positions.T)
        return self._cache["particle_references"]

    def nearest(self, x: Any, y: Any) -> np.ndarray:
        """Index of the nearest kept calibration particle to each (x, y) camera position."""
        if "tree" not in self._cache:
            if self.kept.size == 0:
                raise ValueError("Every calibration particle was culled: nothing to apply.")
            self._cache["tree"] = cKDTree(self.positions[self.kept])
        # huge but finite coordinates overflow the tree's distances (index n = "none found")
        points = np.clip(np.column_stack([x, y]), -1e12, 1e12)
        _, idx = self._cache["tree"].query(points)
        return self.kept[idx]

    def joint_readout(
        self, cols: dict[str, np.ndarray], p: np.ndarray, shift: np.ndarray | None = None,
        *, z_only: bool = False,
    ) -> JointZ:  # fmt: skip
        """The joint readout (:func:`~latentz.calibration.readout.joint_z`, ``z_only`` as
        there) of spots on their particles ``p``, from their columns ``cols``
        (:func:`~latentz.calibration.spot_columns.spot_arrays`), weighted by the covariance of
        their fits (:func:`~latentz.calibration.readout.shape_covariance`: their ``*_err`` and
        ``*_corr`` columns where they carry them) times :attr:`noise_scale` squared; ``shift``
        (n, 3), if given, is taken off their fitted wx, wy, ρ, or (n, planes, 3) off them at each
        of the particle's planes."""
        fitted, cov = self._shape_fit(cols)
        if shift is not None:
            fitted = (fitted if shift.ndim == 2 else fitted[:, None]) - shift
        return joint_z(self.curves_at, self.local.z_nm, usable_scatter(self), p, fitted, cov,
                       z_only=z_only)  # fmt: skip

    def _shape_fit(self, cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The fitted (wx, wy, ρ) (n, 3) of the spots of columns ``cols`` and their covariance
        (n, 3, 3) times :attr:`noise_scale` squared (:func:`~latentz.calibration.readout.
        shape_covariance`: their ``*_err`` and ``*_corr`` columns where they carry them)."""
        params = stacked(cols, PARAMS)
        errors = corr = None
        if all(c in cols for c in ERROR_COLUMNS):
            errors, corr = stacked(cols, ERROR_COLUMNS), stacked(cols, CORRELATION_COLUMNS)
        cov = shape_covariance(params, errors, corr, roi_size=self.roi_size,
                               readnoise=self.camera.readnoise)  # fmt: skip
        return params[:, 4:7], self.noise_scale**2 * cov

    def _profile_bound(self, cols: dict, p: np.ndarray, z: np.ndarray,
                       sigma: np.ndarray) -> np.ndarray:  # fmt: skip
        """``sigma`` (nm), the fit's part of σ_z of the spots of columns ``cols`` read at z on
        particles ``p``, where z is poorly read capped by the 68 % half-width about z of their
        likelihood over the z where a spot in range lies
        (:func:`~latentz.calibration.readout.profile_width` over :meth:`in_range_window`; wx,
        wy, ρ corrected for the spot's brightness as in :meth:`_joint_shape`). Poorly read:
        ``sigma`` wider than the range alone says (:func:`_range_width`), as where the shape
        hardly changes with z, and σ from the curvature (or from σ_s through the inverse, which
        piles the normal's tails at the range's ends) spans it many times. Elsewhere ``sigma``
        stands: there the likelihood of the three widths is narrower than their errors about
        the curves (on a validation microscope, 44 % instead of 56 % of spots covered)."""
        found = np.isfinite(z)
        window = self.in_range_window(np.where(found, p, 0), np.where(found, z, 0.0))
        with np.errstate(invalid="ignore"):
            rows = np.flatnonzero(found & (sigma > _range_width(window)))
        if rows.size == 0:
            return sigma
        part = {k: v[rows] for k, v in cols.items()}
        fitted, cov = self._shape_fit(part)
        shift = self._shape_params_shift(part, p[rows], z[rows])
        if shift is not None:
            fitted = fitted - shift
        window = window[rows]
        width = profile_width(self.curves_at, self.local.z_nm, usable_scatter(self), p[rows],
                              fitted, cov, z[rows], window)  # fmt: skip
        out = sigma.copy()
        out[rows] = np.fmin(sigma[rows], width)
        return out

    def _joint_shape(self, cols: dict, p: np.ndarray) -> tuple[np.ndarray, JointZ]:
        """The joint readout of the spots of columns ``cols`` and the shape value of its z
        (:meth:`_shape_at`). Where the calibration has dimmed refits, the readout is repeated
        with the fitted wx, wy, ρ corrected for the spots' background ratio
        (:meth:`_shape_params_shift`) at the first readout's z."""
        joint = self.joint_readout(cols, p)
        shift = self._shape_params_shift(cols, p, joint.z_nm)
        if shift is not None:
            joint = self.joint_readout(cols, p, shift)
        return self._shape_at(p, joint.z_nm), joint

    def _shape_params_shift(self, cols: dict, p: np.ndarray, z: np.ndarray,
                            plane: np.ndarray | None = None) -> np.ndarray | None:  # fmt: skip
        """(n, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns ``cols`` on
        particles ``p`` at z (nm) (:func:`~latentz.calibration.dimming.shape_shift` of the three
        at once, from one read of :meth:`_dimming_terms`; 0 where unknown), or None where the
        calibration has no dimmed refits or the spots no background. ``plane`` (n,), if given,
        is the index of the particle's plane at z, read without interpolation."""
        from latentz.calibration.dimming import shape_shift

        if "background" not in cols or "dim0_wx" not in self.traces.data:
            return None
        terms = self._dimming_terms(cols["amplitude"], cols["background"], p, z, plane)
        shift = shape_shift(lambda a, wx, wy, rho: np.column_stack([wx, wy, rho]), *terms)
        return np.where(np.isfinite(shift), shift, 0.0)

    def _past_turn(self, cols: dict, p: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(n,) spots (columns ``cols``) read at z (nm) from their one shape value whose fitted
        wx, wy, ρ lie nearest their particle's curves outside the monotonic range of its inverse
        z(s): the joint search over all the particle's planes (:meth:`joint_readout`) puts them
        beyond it, with each plane's curves seen at the spot's brightness there
        (:meth:`_shift_by_plane`) or with the one brightness correction at z. Past the range's
        end the shape value turns back (far from focus a high-NA PSF's fitted widths stop
        growing, or the ROI cuts the spot off), so a spot from there has the shape value of one
        inside it; its widths and ρ together tell the two apart. A dim ring's fit takes its
        core, far narrower than the bright particle's fit at its plane, which the correction at
        each plane shows (full family draw 15: 7 of the 13 spots that the one correction leaves
        in range read over 400 nm off); 4 spots from 1.2 µm below focus on draw 2 lie nearest
        beyond with the one correction alone."""
        out = np.zeros(z.size, dtype=bool)
        found = np.flatnonzero(np.isfinite(z))
        z_range = self.local.shapes[self.shape].z_range
        for start in range(0, found.size, _PLANE_CHUNK):
            rows = found[start : start + _PLANE_CHUNK]
            part = {name: values[rows] for name, values in cols.items()}
            lo, hi = z_range[p[rows]].T
            shifts = [self._shift_by_plane(part, p[rows])]
            if shifts[0] is not None:  # without dimmed refits or background both are None
                shifts.append(self._shape_params_shift(part, p[rows], z[rows]))
            for shift in shifts:
                joint = self.joint_readout(part, p[rows], shift, z_only=True)
                with np.errstate(invalid="ignore"):
                    out[rows] |= (joint.z_nm < lo) | (joint.z_nm > hi)
        return out

    def _shift_by_plane(self, cols: dict, p: np.ndarray) -> np.ndarray | None:
        """(n, planes, 3) brightness shift of the fitted wx, wy, ρ of the spots of columns
        ``cols`` on particles ``p`` at each of the particle's planes
        (:meth:`_shape_params_shift` there), or None where the calibration has no dimmed refits
        or the spots no background."""
        if "background" not in cols or "dim0_wx" not in self.traces.data:
            return None
        planes = self.local.z_nm[p]
        n, n_z = planes.shape
        rows = {name: np.repeat(cols[name], n_z) for name in ("amplitude", "background")}
        index = np.tile(np.arange(n_z), n)
        shift = self._shape_params_shift(rows, np.repeat(p, n_z), planes.ravel(), index)
        return shift.reshape(n, n_z, 3)

    def z_beyond_range(self, spots: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """Where one emitter beyond the calibrated range would be: for spots (a fit table: x, y,
        amplitude, wx, wy, ρ and, where it has them, their ``*_err``, ``*_corr`` and
        background columns), the z (nm) of the joint readout over all their particle's planes
        (:meth:`joint_readout`, brightness-corrected) where it lies outside that particle's
        monotonic range (NaN elsewhere), and the particle. The calibration imaged its own
        particles there: far from focus a real PSF is a ring that one Gaussian fits poorly."""
        cols = spot_arrays(spots)
        located = np.logical_and.reduce([np.isfinite(cols[c]) for c in SPOT_COLUMNS])
        p = self.nearest(np.where(located, cols["x"], 0.0), np.where(located, cols["y"], 0.0))
        z = self._joint_shape(cols, p)[1].z_nm
        lo, hi = self.local.shapes[self.shape].z_range[p].T
        with np.errstate(invalid="ignore"):
            outside = located & ((z < lo) | (z > hi))
        return np.where(outside, z, np.nan), p

    def _shape_at(self, p: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The shape value whose inverse z(s) of particle ``p`` gives ``z`` (nm): Newton steps
        on z(s) from the forward model s(z); NaN where z is outside the inverse's range."""
        model = self.local.shapes[self.shape]
        inverse, slope = model.inverse[p], error_model(self, "z")[2][p]
        target = np.where(np.isfinite(z), z, 0.0)
        s = model.forward[p](target)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for _ in range(4):
                s = s - (inverse(s) - target) / slope(s)
            hit = np.abs(inverse(s) - target) < 0.5
        return np.where(np.isfinite(z) & hit & inverse.contains(s) & inverse.valid, s, np.nan)

    def apply(
        self,
        spots: pd.DataFrame,
        *,
        amplitude_reference: str = "calibration",
        error_parts: bool = False,
        z_readout: str = "shape",
        errors: bool = True,
        lateral_reference: str = "place",
    ) -> pd.DataFrame:
        """Localize spots in 3D with the widefield models (or the nearest particle's).

        z comes from the field model of z(x', y'; s) at the spot's shape value s (see
        ``z_readout``), and the lateral correction from the field models of Δx', Δy' at that z
        (paper Fig. 4); with ``field_model="nearest"``, from the nearest calibration particle's
        local models.
        Uncertainties combine the spots' own Cramér–Rao errors (when they carry them), the
        nearest particle's local model errors and the field model's cross-validated error
        (:mod:`latentz.calibration.errors`); the spots' own part is scaled by
        :attr:`noise_scale_by_z` where the calibration images show less noise than their fits
        say.

        Parameters
        ----------
        spots : DataFrame
            From ``localize`` / ``fit_rois``: x, y (camera pixels), amplitude, wx, wy, rho, and
            optionally their ``*_err`` columns (then errors are propagated per spot).
        amplitude_reference : {"calibration", "particle"}
            For A-normalised shapes ("rho_A", "auto_A"): the calibration particles' A_{ρ=ρ0}
            about the spot's nearest particle (:attr:`reference_field`: emitters as bright as
            the calibration particles, whose own spread in brightness ``z_err_nm`` then
            includes), or that of each emitter's own track (the spot with the smallest |ρ| in
            its ``particle`` group).
        z_readout : {"shape", "joint"}
            How the spot's shape becomes z: "shape", its one shape value; or "joint", its fitted
            wx, wy, ρ against its particle's curves of the three, weighted by their covariance
            (:mod:`~latentz.calibration.readout`), passed on as the shape value of that z.
            With "joint", where a second z fits within Δχ² < 1 (the sign of defocus unresolved:
            weak astigmatism, dim spots) the better one is reported and the fit's part of
            ``z_err_nm`` reaches the other.
        error_parts : bool
            Also return what ``z_err_nm`` is made of: ``z_err_fit_nm``, the spot's own fit
            precision (NaN for spots without ``*_err`` columns), and ``z_err_field_nm``, the
            part that varies across the field (field model, dimming transfer, distance to the
            particle); the local model's σ and the amplitude reference's scatter are the
            rest, in quadrature.
        errors : bool
            False: the places alone, without the ``*_err_nm`` columns, whose computation is
            skipped (for a caller that only asks where the spots are).
        lateral_reference : {"place", "focus"}
            What ``x_err_nm``, ``y_err_nm`` are errors against: "place", where the emitter is,
            so that they hold the calibration particles' own reference (their fitted centre at
            best focus, off their place under coma: :meth:`reference_sigma_nm`); or "focus", the
            paper's convention, where a particle is its fitted centre at best focus and that
            reference is exact.

        Returns
        -------
        DataFrame
            A copy of ``spots`` with x_nm, y_nm, z_nm, x_err_nm, y_err_nm, z_err_nm (not with
            ``errors=False``), in_range and cal_particle (index of the calibration particle
            used). Outside that particle's calibrated range (its monotonic range, or widths
            over :data:`BEYOND_WIDTH` times its curves' at the z read, or, with the one shape
            value, fitted wx, wy, ρ nearest its curves beyond that range (:meth:`_past_turn`):
            a spot beyond the range whose shape value mimics one inside it), z_nm and the
            corrected positions are NaN and in_range is False.
        """
        if error_parts and not errors:
            raise ValueError("error_parts=True needs the errors: leave errors=True.")
        check_choice("lateral_reference", lateral_reference, ("place", "focus"))
        placed = self._place(spots, amplitude_reference, z_readout)
        out = {"x_nm": placed.x_nm, "y_nm": placed.y_nm, "z_nm": placed.z}
        if errors:
            out = self._errors(placed, z_readout, error_parts, lateral_reference == "place")
        return with_columns(spots, out | {"in_range": placed.in_range, "cal_particle": placed.p})

    def _place(self, spots: pd.DataFrame, amplitude_reference: str, z_readout: str) -> _Placed:
        """Where :meth:`apply` puts ``spots`` (its checks first), before their errors."""
        check_columns("spots", spots, SPOT_COLUMNS)
        check_roi_size(spots.attrs.get("roi_size"), self.roi_size)
        cols = spot_arrays(spots)
        check_widths(np.column_stack([cols["wx"], cols["wy"]]), self.width_range_px)
        check_choice("amplitude_reference", amplitude_reference, ("calibration", "particle"))
        check_choice("z_readout", z_readout, Z_READOUTS)
        # a spot with any non-finite fit value is a broken fit: never in range
        located = np.logical_and.reduce([np.isfinite(cols[c]) for c in SPOT_COLUMNS])
        p = self.nearest(np.where(located, cols["x"], 0.0), np.where(located, cols["y"], 0.0))
        ref, ref_scatter = self._amplitude_reference(spots, cols, p, amplitude_reference)
        joint = None
        if z_readout == "joint":
            s, joint = self._joint_shape(cols, p)
            ref_scatter = 0.0  # z does not use the amplitude
        else:
            s = shape_value(self.shape, cols["wx"], cols["wy"], cols["rho"], cols["amplitude"],
                            theta=self.local.theta, amplitude_ref=ref)  # fmt: skip
        z, shifts, in_range = self._locate(s, p, cols, located)
        if joint is None and "background" in cols and "dim0_wx" in self.traces.data:
            s = s - self._dimming_shift(cols["amplitude"], cols["background"], p, z, ref)
            z, shifts, in_range = self._locate(s, p, cols, located)
        in_range &= ~self._beyond_range(cols, p, z)
        if joint is None:
            in_range &= ~self._past_turn(cols, p, np.where(in_range, z, np.nan))
        z = np.where(in_range, z, np.nan)
        px = self.camera.pixel_size_nm
        dimmed = None  # the spot's own brightness moves its fitted centre (coma)
        if "background" in cols and "dim0_dx" in self.traces.data:
            dimmed = self._position_shifts(cols["amplitude"], cols["background"], p, z)
        place = {}
        for axis, delta in (("x", self.local.dx), ("y", self.local.dy)):
            shift = delta[p](np.where(in_range, z, 0.0)) if shifts is None else shifts[axis]
            if dimmed is not None:
                shift = shift + dimmed[axis]
            place[axis] = np.where(in_range, (cols[axis] - shift) * px, np.nan)
        return _Placed(cols, p, s, z, in_range, place["x"], place["y"], joint, ref, ref_scatter)

    def _errors(self, placed: _Placed, z_readout: str, error_parts: bool,
                reference: bool) -> dict[str, np.ndarray]:  # fmt: skip
        """:meth:`apply`'s columns of the ``placed`` spots, their places with their errors
        (nm), in order: x_nm, x_err_nm, y_nm, y_err_nm, z_nm, z_err_nm, and with
        ``error_parts`` z_err_fit_nm and z_err_field_nm; laterally with the particles' own
        reference (``reference``) or without."""
        cols, p, z, in_range = placed.cols, placed.p, placed.z, placed.in_range
        distance = np.hypot(*(np.column_stack([cols["x"], cols["y"]]) - self.positions[p]).T)
        at = row_weights(self.local.z_nm, p, z)
        z_err, z_fit = self._z_error(cols, placed.s, p, z, in_range, at, placed.ref,
                                     placed.ref_scatter, placed.joint)  # fmt: skip
        out = {}
        for axis, place in (("x", placed.x_nm), ("y", placed.y_nm)):
            err = self._lateral_error(axis, cols, p, z, in_range, at, z_err, distance)
            if reference:
                err = combine(err, self.reference_sigma_nm(axis))
            out[f"{axis}_nm"] = place
            out[f"{axis}_err_nm"] = np.where(in_range, err, np.nan)
        out["z_nm"] = z
        z_field = self._z_field_error(cols, z, distance, z_readout)
        out["z_err_nm"] = np.where(in_range, combine(z_err, z_field), np.nan)
        if error_parts:
            out["z_err_fit_nm"] = np.where(in_range, z_fit, np.nan)
            out["z_err_field_nm"] = np.where(in_range, z_field, np.nan)
        return out

    def _beyond_range(self, cols: dict, p: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(n,) spots at z (nm) on particles ``p`` whose mean fitted width (``cols``' wx, wy,
        px) exceeds :data:`BEYOND_WIDTH` times the particle's curves at z (:meth:`curves_at`):
        spots past the end of the monotonic range whose shape value mimics one inside it."""
        found = np.isfinite(z)
        out = np.zeros(z.size, dtype=bool)
        if found.any():
            c = self.curves_at(p[found], z[found])
            width = np.abs(cols["wx"][found]) + np.abs(cols["wy"][found])
            with np.errstate(invalid="ignore"):
                out[found] = width > BEYOND_WIDTH * (np.abs(c["wx"]) + np.abs(c["wy"]))
        return out

    def _z_field_error(self, cols: dict, z: np.ndarray, distance: np.ndarray,
                       readout: str) -> np.ndarray:  # fmt: skip
        """The part of σ_z (nm) that varies across the field, as held-out particles measure
        it: the field model's cross-validated error with the dimming correction's transfer
        (at the spot's background ratio c), or, where larger, the error of held-out particles
        seen as emitters of that c and localized by neighbours as far away as the spot is from
        its particle with the z ``readout`` (:meth:`_pair_sigma`). That is ``nearest``'s error
        (with the joint readout, the pairs' alone: the cross-validation and the transfer are
        the shape value's, and the pairs hold both for the joint readout): for another field
        model it counts only beyond the distances its cross-validation held out (above their
        90th percentile), where the model extrapolates; ``cols``: the spots' columns
        (:func:`~latentz.calibration.spot_columns.spot_arrays`)."""
        c_spot = None
        if "background" in cols and "dim0_wx" in self.traces.data:
            c_spot = background_ratio(cols["background"], cols["amplitude"],
                                      self.camera.readnoise)  # fmt: skip
        pair = self._pair_sigma(z, c_spot, distance, readout)
        if readout == "joint" and self.field_model == "nearest":
            return pair
        field = self._field_sigma("z", z, distance)
        if c_spot is not None:
            field = combine(field, self._transfer_sigma(z, c_spot))
        pair = np.fmax(field, pair)
        if self.field_model == "nearest":
            return pair
        held = self.crossval_of(self.field_model)["distance_px"].to_numpy()
        return np.where(distance > np.quantile(held, 0.9), pair, field)

    def _amplitude_reference(
        self, spots: pd.DataFrame, cols: dict, p: np.ndarray, amplitude_reference: str
    ) -> tuple[np.ndarray, float]:
        """Each spot's A_{ρ=ρ0} for the shape value (:meth:`apply`'s ``amplitude_reference``),
        and the relative scatter of the calibration particles' reference about it."""
        shape = self.shape
        if uses_amplitude(shape) and amplitude_reference == "particle":
            check_columns("spots", spots, ("particle",))
            return _track_reference(shape, spots, cols, self.local.theta), 0.0
        if uses_amplitude(shape):  # the reference about the spot's nearest particle
            return self._particle_references()[p], self.reference_field.scatter
        return self.local.shapes[shape].amplitude_ref[p], 0.0

    def _z_error(
        self,
        cols: dict[str, np.ndarray],
        s: np.ndarray,
        p: np.ndarray,
        z: np.ndarray,
        in_range: np.ndarray,
        at: tuple[np.ndarray, np.ndarray, np.ndarray],
        ref: np.ndarray,
        ref_scatter: float,
        joint: JointZ | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """σ_z (nm) before the field model's part: the spot's own (propagated from its fit
        errors where it carries them, else the calibration's at z) with the particle's model
        error, and the amplitude reference's scatter; and the fit's part alone (NaN where the
        spots carry no fit errors). With the ``joint`` readout, the fit's part is its σ or,
        where larger, its spread over a second minimum; with either readout, at most the
        likelihood's width over the particle's range (:meth:`_profile_bound`). ``cols``: the
        spots' columns (:func:`~latentz.calibration.spot_columns.spot_arrays`), NaN for a
        correlation they lack."""
        model_part = model_sigma(self, "z", p, z, at)
        fit_part = np.full(len(s), np.nan)
        if all(c in cols for c in ERROR_COLUMNS):
            if joint is None:  # scaled about each z (noise_scale_by_z)
                params, errors = stacked(cols, PARAMS), stacked(cols, ERROR_COLUMNS)
                fit_part = noise_scale_at(self, z) * fit_part_z(
                    self, params, errors, stacked(cols, CORRELATION_COLUMNS), p,
                    np.where(in_range, s, 0.0), ref)  # fmt: skip
            else:  # its fit covariance already scaled by noise_scale (joint_readout)
                fit_part = np.fmax(joint.sigma_nm, joint.spread_nm)
            fit_part = self._profile_bound(cols, p, np.where(in_range, z, np.nan), fit_part)
            z_err = np.hypot(fit_part, model_part)
        else:
            z_err = interp_rows(self.local.z_nm, error_model(self, "z")[0], p, z, at)
        if ref_scatter > 0:  # s ∝ A_ref: an error δ in ln A_ref moves s by s·δ; NaN: unknown
            s_in = np.where(in_range, s, 0.0)
            z_err = combine(z_err, through_inverse(self, p, s_in, np.abs(s_in) * ref_scatter))
        return z_err, fit_part

    def _lateral_error(
        self,
        axis: str,
        cols: dict,
        p: np.ndarray,
        z: np.ndarray,
        in_range: np.ndarray,
        at: tuple[np.ndarray, np.ndarray, np.ndarray],
        z_err: np.ndarray,
        distance: np.ndarray,
    ) -> np.ndarray:
        """σ of the corrected ``axis`` position (nm) of the spots of columns ``cols``: the
        spot's own, the particle's model error and lack of fit, its σ_z before the field's part
        (``z_err``; the field's reaches x, y in the field model's held-out errors) through the
        particle's correction (:func:`~latentz.calibration.errors.spread_through` over the z
        where a spot in range lies, :meth:`in_range_window`: the width that holds 68 % of the
        normal's weight, not the RMS, which the curve's steep ends rule), the field model's
        (:meth:`_field_sigma`); the particles' own reference (:meth:`reference_sigma_nm`) is
        :meth:`apply`'s to add."""
        px = self.camera.pixel_size_nm
        model = self.local.dx if axis == "x" else self.local.dy
        z_in = np.where(in_range, z, 0.0)
        from_z = spread_through(model[p], z_in, np.where(in_range, z_err, 0.0),
                                self.in_range_window(p, z_in), covering=True)  # fmt: skip
        model_d = model_sigma(self, axis, p, z, at)
        if f"{axis}_err" in cols:
            own = cols[f"{axis}_err"]
        else:
            own = interp_rows(self.local.z_nm, error_model(self, axis)[0], p, z, at)
        field_d = self._field_sigma(axis, z, distance)  # nm
        lack = interp_rows(self.local.z_nm, lack_of_fit(self, axis), p, z, at)
        return combine(own * px, model_d * px, lack * px, from_z * px, field_d)


def _range_width(window: np.ndarray) -> np.ndarray:
    """What a spot's range ``window`` ((n, 2), nm) alone says of its z: the 68 % half-width
    (nm) of a uniform z over it, about its middle."""
    return ONE_SIGMA * (window[:, 1] - window[:, 0]) / 2


class _Placed(NamedTuple):
    """Where :meth:`Calibration.apply` puts spots, and what their errors read: the spots'
    columns ``cols`` (:func:`~latentz.calibration.spot_columns.spot_arrays`), nearest
    particles ``p``, shape values ``s``, ``z`` (nm, NaN out of range), ``in_range``, the
    corrected ``x_nm``, ``y_nm``, the joint readout (None with the one shape value) and the
    amplitude reference ``ref`` with its relative scatter."""

    cols: dict[str, np.ndarray]
    p: np.ndarray
    s: np.ndarray
    z: np.ndarray
    in_range: np.ndarray
    x_nm: np.ndarray
    y_nm: np.ndarray
    joint: JointZ | None
    ref: np.ndarray
    ref_scatter: float


def _interp_levels(log_c: np.ndarray, by_level: np.ndarray, c_spot: np.ndarray) -> np.ndarray:
    """Values ``by_level`` (levels, spots) at each spot's ratio ``c_spot``: linear in log c
    between the levels ``log_c`` (ascending), held at the ends; the lowest where c is unknown."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.log(np.asarray(c_spot, dtype=np.float64))
    x = np.clip(np.where(np.isfinite(x), x, log_c[0]), log_c[0], log_c[-1])
    j = np.clip(np.searchsorted(log_c, x), 1, log_c.size - 1)
    t = (x - log_c[j - 1]) / (log_c[j] - log_c[j - 1])
    spots = np.arange(x.size)
    return (1 - t) * by_level[j - 1, spots] + t * by_level[j, spots]


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

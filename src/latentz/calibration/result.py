"""The result of calibration, and 3D localization with it (paper Fig. 4, Supp. Table 2).

A :class:`Calibration` holds the traces and local models of every calibration particle on the
tilt-corrected z axis (z = 0 is the focal surface of the calibration particles after levelling)
and the widefield models built from them. :meth:`Calibration.apply` localizes spots in 3D: z from
the field model of z at the spot's shape value (or, with ``z_readout="joint"``, the value whose
z its fitted wx, wy, ρ fit best jointly, :mod:`latentz.calibration.readout`), then the lateral
correction at that z; shape values outside what the particles cover are flagged, never
extrapolated. It runs in two steps: where the spots go (:mod:`latentz.calibration.placing`)
and what their errors are made of (:mod:`latentz.calibration.spot_errors`).
:meth:`Calibration.local_z` and :meth:`Calibration.local_delta` evaluate every particle's models
at once, for the widefield models. The file layout is described in docs/file-format.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz._shared.columns import with_columns
from latentz._shared.validate import check_choice
from latentz.calibration.brightness_shifts import shape_params_shift
from latentz.calibration.errors import DEPTH_FRACTION, reference_sigma
from latentz.calibration.fieldmodels import FIELD_MODEL_KINDS
from latentz.calibration.joint_readout import joint_readout
from latentz.calibration.local import LocalModels, focus_depth_nm, row_mean
from latentz.calibration.noise_scale import noise_scale, noise_scale_by_z
from latentz.calibration.particle_curves import curves_at
from latentz.calibration.particle_table import particle_table
from latentz.calibration.placing import place, z_beyond_range
from latentz.calibration.readout import SHAPE_PARAMS, JointZ
from latentz.calibration.reference import ReferenceField
from latentz.calibration.spot_errors import spot_errors
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import Traces
from latentz.camera import Camera

__all__ = ["Calibration", "FIELD_CHOICES", "FIELD_MODELS", "PAPER_SHAPES"]

FIELD_MODELS = FIELD_MODEL_KINDS
#: What ``field_model`` accepts: a model, or "auto" (the best by cross-validation).
FIELD_CHOICES = (*FIELD_MODELS, "auto")
PAPER_SHAPES = ("rho", "rho_w", "rho_A")


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
        (:func:`~latentz.calibration.brightness_shifts.
        shape_params_shift`): the shapes their particle's own fit would show at their
        z, comparable with :meth:`curves_at`; None where the calibration has no dimmed refits
        or the spots no ``background``."""
        cols = {c: located[c].to_numpy(float) for c in ("amplitude", "background")
                if c in located.columns}  # fmt: skip
        shift = shape_params_shift(self, cols, located["cal_particle"].to_numpy(int),
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

    @property
    def reference_field(self) -> ReferenceField:
        """A-normalised shapes' reference amplitude across the field, from the kept particles
        (:class:`~latentz.calibration.reference.ReferenceField`)."""
        if "reference_field" not in self._cache:
            rows = self.kept
            ref = self.local.shapes[self.shape].amplitude_ref[rows]
            self._cache["reference_field"] = ReferenceField(self.positions[rows], ref)
        return self._cache["reference_field"]

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
        return joint_readout(self, cols, p, shift, z_only=z_only)

    def z_beyond_range(self, spots: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """Where one emitter beyond the calibrated range would be: for spots (a fit table: x, y,
        amplitude, wx, wy, ρ and, where it has them, their ``*_err``, ``*_corr`` and
        background columns), the z (nm) of the joint readout over all their particle's planes
        (:meth:`joint_readout`, brightness-corrected) where it lies outside that particle's
        monotonic range (NaN elsewhere), and the particle. The calibration imaged its own
        particles there: far from focus a real PSF is a ring that one Gaussian fits poorly."""
        return z_beyond_range(self, spots)

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
            over :data:`~latentz.calibration.placing.BEYOND_WIDTH` times its curves' at the z
            read, or, with the one shape value, fitted wx, wy, ρ nearest its curves beyond that
            range (:mod:`~latentz.calibration.placing`): a spot beyond the range whose shape
            value mimics one inside it), z_nm and the corrected positions are NaN and in_range
            is False.
        """
        if error_parts and not errors:
            raise ValueError("error_parts=True needs the errors: leave errors=True.")
        check_choice("lateral_reference", lateral_reference, ("place", "focus"))
        placed = place(self, spots, amplitude_reference, z_readout)
        out = {"x_nm": placed.x_nm, "y_nm": placed.y_nm, "z_nm": placed.z}
        if errors:
            out = spot_errors(self, placed, z_readout, error_parts, lateral_reference == "place")
        return with_columns(spots, out | {"in_range": placed.in_range, "cal_particle": placed.p})

"""Field models: a quantity known at calibration particles, as a function of field position.

The widefield calibration (Supp. Table 2, METHOD.md items 15-20) turns values known at the
calibration particles (z for a shape value, or Delta x', Delta y' for a z) into functions of the
lateral position. The paper compares three models, all behind one interface here:

``"zernike"``
    Least-squares fit of the first ``n_terms`` Noll Zernike polynomials on the disk that
    circumscribes the field (:mod:`latentz.zernike`). Its error estimate is the fit residual at
    each particle.
``"natural"``
    Natural-neighbour (Sibson) interpolation (MetPy's ``natural_neighbor_to_points``); NaN outside
    the convex hull of the valid particles, never extrapolated. Error estimate: leave-one-out.
``"nearest"``
    The value of the nearest valid particle (``scipy.spatial.cKDTree``). Leave-one-out errors.

One model holds ``m`` columns at once (for example one per tabulated shape value), each with its
own set of valid particles. All three are linear in the values, so the work that depends only on
which particles are valid (a pseudo-inverse, a triangulation, a tree) is done once per distinct
validity pattern and then applied to every column sharing it.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
import pandas as pd
from metpy.interpolate import natural_neighbor_to_points
from scipy.sparse import csr_matrix
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree
from scipy.stats import kurtosis

from latentz._shared.validate import check_array, check_choice, check_int, check_positive
from latentz.zernike import field_to_disk, truncated_lstsq_operator, zernike_design

__all__ = ["FieldModel", "FIELD_MODEL_KINDS", "field_errors"]

FIELD_MODEL_KINDS = ("zernike", "natural", "nearest")
_FORMAT = 1  # version of the representation returned by FieldModel.as_arrays
_CHUNK = 8192  # query points per block
_NN_CHUNK = 512  # query points per MetPy call


def _as_points(x: Any, y: Any, names: tuple[str, str]) -> tuple[np.ndarray, np.ndarray]:
    x = np.atleast_1d(check_array(names[0], x, ndim=(0, 1), dtype_kind="uif", allow_empty=True))
    y = np.atleast_1d(check_array(names[1], y, ndim=(0, 1), dtype_kind="uif", allow_empty=True))
    if x.shape != y.shape:
        raise ValueError(f"Expected `{names[1]}` to have shape {x.shape}, got {y.shape}.")
    return x.astype(np.float64), y.astype(np.float64)


# --------------------------------------------------------------------------------------------
# Interpolation weights. Each returns (point, particle, weight) triplets and a mask of points
# where the interpolant is defined; the prediction is sum(weight * value[particle]).


def _nearest_weights(points: np.ndarray, queries: np.ndarray):
    _, idx = cKDTree(points).query(queries)
    k = np.arange(len(queries))
    return k, idx, np.ones(len(queries)), np.ones(len(queries), dtype=bool)


def _metpy_rows(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Sibson coordinates (n_queries, n_points) of queries strictly inside the hull, via MetPy.

    MetPy's interpolation is linear in ``values``, so interpolating the identity matrix returns
    each query's natural-neighbour weights. A query MetPy cannot process (a degenerate Voronoi
    polygon) gets a row of NaN.
    """
    eye = np.eye(len(points))
    try:
        return np.asarray(natural_neighbor_to_points(points, eye, queries), dtype=np.float64)
    except ValueError:  # a failed point came back as a scalar NaN: redo one at a time
        rows = np.full((len(queries), len(points)), np.nan)
        for i in range(len(queries)):
            row = np.asarray(natural_neighbor_to_points(points, eye, queries[i : i + 1]))
            if row.shape == (1, len(points)):
                rows[i] = row[0]
        return rows


def _natural_weights(points: np.ndarray, queries: np.ndarray):
    n_q = len(queries)
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros(0))
    if len(points) < 3:
        return *empty, np.zeros(n_q, dtype=bool)
    try:
        hull = ConvexHull(points)
    except QhullError:  # all particles on a line: no triangle, no interpolant
        return *empty, np.zeros(n_q, dtype=bool)
    # Inside the hull (edges included). Unlike Delaunay.find_simplex this needs no LAPACK call,
    # whose thread start-up dominates for the many small point sets of leave-one-out.
    scale = max(float(np.ptp(points)), 1.0)
    ok = np.all(queries @ hull.equations[:, :2].T + hull.equations[:, 2] <= 1e-12 * scale, axis=1)
    dist, near = cKDTree(points).query(queries)
    at_site = ok & (dist <= 1e-9 * scale)
    ki, kj, kw = [np.flatnonzero(at_site)], [near[at_site]], [np.ones(int(at_site.sum()))]
    todo = np.flatnonzero(ok & ~at_site)
    for start in range(0, todo.size, _NN_CHUNK):
        sel = todo[start : start + _NN_CHUNK]
        rows = _metpy_rows(points, queries[sel])
        failed = ~np.all(np.isfinite(rows), axis=1)
        ok[sel[failed]] = False
        r, c = np.nonzero(np.where(np.isfinite(rows), rows, 0.0))
        ki.append(sel[r])
        kj.append(c)
        kw.append(rows[r, c])
    return np.concatenate(ki), np.concatenate(kj), np.concatenate(kw), ok


def _natural_loo(points: np.ndarray):
    """Leave-one-out Sibson weights: particle ``i`` predicted from all the others.

    Removing particle ``i`` only changes the triangulation inside its star, so the weights are
    computed from its neighbours and their neighbours in the Delaunay triangulation, which
    reproduces the interpolant of all other particles at ``i`` exactly.
    """
    n = len(points)
    ki, kj, kw = [], [], []
    ok = np.zeros(n, dtype=bool)
    if n < 4:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), ok
    try:
        indptr, nbr = Delaunay(points).vertex_neighbor_vertices
    except QhullError:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), ok
    for i in range(n):
        ring = nbr[indptr[i] : indptr[i + 1]]
        local = np.unique(np.concatenate([ring] + [nbr[indptr[j] : indptr[j + 1]] for j in ring]))
        local = local[local != i]
        _, pj, w, inside = _natural_weights(points[local], points[i : i + 1])
        ok[i] = inside[0]
        ki.append(np.full(pj.size, i))
        kj.append(local[pj])
        kw.append(w)
    return np.concatenate(ki), np.concatenate(kj), np.concatenate(kw), ok


def _nearest_loo(points: np.ndarray):
    n = len(points)
    if n < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(n, dtype=bool)
    _, idx = cKDTree(points).query(points, k=2)
    other = np.where(idx[:, 0] == np.arange(n), idx[:, 1], idx[:, 0])
    return np.arange(n), other, np.ones(n), np.ones(n, dtype=bool)


_WEIGHTS = {"natural": _natural_weights, "nearest": _nearest_weights}
_LOO = {"natural": _natural_loo, "nearest": _nearest_loo}


# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FieldModel:
    """``m`` scalar fields over the image field, each known at a subset of particles.

    Build with :meth:`FieldModel.from_estimate`; evaluate by calling; :meth:`residuals` gives the
    error estimate at each particle; :meth:`as_arrays` / :meth:`from_arrays` serialise.

    Attributes
    ----------
    kind : str
        ``"zernike"``, ``"natural"`` or ``"nearest"``.
    x_px, y_px : ndarray (n,)
        Particle positions, pixels.
    values : ndarray (n, m)
        Values at the particles (NaN where not valid).
    valid : ndarray (n, m) of bool
        Which particles each column uses.
    field_shape : (int, int)
        ``(H, W)`` of the field, pixels.
    options : dict
        ``n_terms``, ``points_per_term``, ``max_condition`` (Zernike) and ``squeeze`` (the values
        were one-dimensional, so evaluation returns one-dimensional arrays).
    coefficients : ndarray (n_terms, m) or None
        Zernike coefficients in Noll order (zeros beyond each column's effective number of terms,
        NaN for a column that could not be fitted); ``None`` for interpolants.
    n_terms_effective : ndarray (m,) of int or None
        Terms actually fitted per column (Zernike); ``None`` for interpolants.
    condition : ndarray (m,) or None
        Condition number of each column's design matrix (Zernike).

    Examples
    --------
    >>> x, y = np.array([10.0, 50.0, 90.0, 30.0]), np.array([10.0, 80.0, 20.0, 60.0])
    >>> model = FieldModel.from_estimate(x, y, 2.0 * x, kind="nearest", field_shape=(100, 100))
    >>> model(np.array([12.0, 88.0]), np.array([11.0, 25.0])).tolist()
    [20.0, 180.0]
    >>> model.residuals().tolist()  # leave-one-out: value minus the nearest other particle's
    [-40.0, 40.0, 80.0, -40.0]
    """

    kind: str
    x_px: np.ndarray
    y_px: np.ndarray
    values: np.ndarray
    valid: np.ndarray
    field_shape: tuple[int, int]
    options: Mapping[str, Any]
    coefficients: np.ndarray | None = None
    n_terms_effective: np.ndarray | None = None
    condition: np.ndarray | None = None
    _patterns: np.ndarray = field(init=False, repr=False)
    _pattern_of: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        patterns, inverse = np.unique(self.valid.T, axis=0, return_inverse=True)
        object.__setattr__(self, "_patterns", patterns)
        object.__setattr__(self, "_pattern_of", inverse.ravel())
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))
        arrays = ("x_px", "y_px", "values", "valid", "coefficients", "n_terms_effective")
        for name in (*arrays, "condition"):
            arr = getattr(self, name)
            if arr is not None:
                arr.flags.writeable = False

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_estimate(
        cls,
        x_px: np.ndarray,
        y_px: np.ndarray,
        values: np.ndarray,
        *,
        kind: str,
        field_shape: tuple[int, int],
        valid: np.ndarray | None = None,
        n_terms: int = 400,
        points_per_term: float = 2.0,
        max_condition: float = 1e8,
    ) -> FieldModel:
        """Build a field model from values at particle positions.

        Parameters
        ----------
        x_px, y_px : ndarray (n,)
            Particle positions in pixels, inside the field and all distinct.
        values : ndarray (n,) or (n, m)
            Values at the particles, any unit; ``m`` columns are modelled independently.
        kind : {"zernike", "natural", "nearest"}
        field_shape : (int, int)
            ``(H, W)`` of the field, pixels.
        valid : ndarray of bool, same shape as ``values``, optional
            Which particles each column uses; default: where ``values`` is finite. Values must be
            finite wherever ``valid`` is True.
        n_terms : int
            Zernike only: Noll indices ``1 ... n_terms`` (paper: 400).
        points_per_term : float
            Zernike only, >= 1. A column with ``n_valid`` particles uses at most
            ``min(n_terms, floor(n_valid / points_per_term))`` terms, so that its residuals keep
            degrees of freedom to estimate the error (default 2: half the data are left over).
        max_condition : float
            Zernike only. Of those, the column uses the largest number of leading (Noll-ordered)
            terms whose design matrix has a condition number <= ``max_condition``. A column left
            with no term is NaN. All reductions below ``n_terms`` are reported by one
            ``UserWarning``; :attr:`n_terms_effective` gives the terms used.

        Returns
        -------
        FieldModel
        """
        kind = check_choice("kind", kind, FIELD_MODEL_KINDS)
        x, y = _as_points(x_px, y_px, ("x_px", "y_px"))
        if x.size == 0:
            raise ValueError("Expected at least one particle, got empty `x_px`.")
        field_to_disk(x, y, field_shape=field_shape)  # checks field_shape and the range
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("Expected `x_px` and `y_px` to be finite.")
        if np.unique(np.column_stack([x, y]), axis=0).shape[0] != x.size:
            raise ValueError("Expected distinct particle positions; `x_px`, `y_px` repeat a point.")
        vals = check_array("values", values, ndim=(1, 2), dtype_kind="uif").astype(np.float64)
        squeeze = vals.ndim == 1
        vals = vals.reshape(vals.shape[0], -1)
        if vals.shape[0] != x.size:
            raise ValueError(
                f"Expected `values` to have {x.size} rows (one per particle), got {vals.shape}."
            )
        if valid is None:
            mask = np.isfinite(vals)
        else:
            mask = np.asarray(valid)
            if mask.dtype != bool:
                raise TypeError(f"Expected `valid` to be boolean, got dtype {mask.dtype}.")
            mask = mask.reshape(mask.shape[0], -1) if mask.ndim else mask
            if mask.shape != vals.shape:
                raise ValueError(
                    f"Expected `valid` to have the shape of `values` {vals.shape}, "
                    f"got {np.shape(valid)}."
                )
            if not np.all(np.isfinite(vals[mask])):
                raise ValueError("Expected `values` to be finite wherever `valid` is True.")
        vals = np.where(mask, vals, np.nan)
        h, w = int(field_shape[0]), int(field_shape[1])
        options: dict[str, Any] = {"squeeze": squeeze}
        fit: dict[str, Any] = {}
        if kind == "zernike":
            options["n_terms"] = check_int("n_terms", n_terms, minimum=1)
            options["points_per_term"] = check_positive("points_per_term", points_per_term)
            if options["points_per_term"] < 1:
                raise ValueError(
                    f"Expected `points_per_term` to be >= 1 (no more terms than particles), "
                    f"got {points_per_term!r}."
                )
            options["max_condition"] = check_positive("max_condition", max_condition)
            fit = _fit_zernike(x, y, vals, mask, (h, w), **{k: options[k] for k in _ZOPTS})
        return cls(kind, x, y, vals, mask, (h, w), options, **fit)

    # ---------------------------------------------------------------- evaluation
    @property
    def n_particles(self) -> int:
        return self.x_px.size

    @property
    def n_columns(self) -> int:
        return self.values.shape[1]

    def __call__(
        self, x_px: Any, y_px: Any, *, columns: Any = None, design: np.ndarray | None = None
    ) -> np.ndarray:
        """Evaluate the model at field positions.

        Parameters
        ----------
        x_px, y_px : float or ndarray (n_points,)
            Positions in pixels, inside the field (pixel edges included). NaN gives NaN.
        columns : ndarray (n_points,) or (n_points, k) of int, optional
            If given, point ``i`` is evaluated only in column ``columns[i]`` (or in the ``k``
            columns ``columns[i, :]``, e.g. the two tabulated columns around a spot's shape
            value).
        design : ndarray (n_points, >= p), optional
            Zernike only: ``zernike_design(x_px, y_px, field_shape=..., n_terms=p)`` computed
            once and shared by several models at the same points, with ``p`` at least
            ``max(n_terms_effective)`` of each.

        Returns
        -------
        ndarray
            ``(n_points, m)``; or the shape of ``columns``; or ``(n_points,)`` if the model was
            estimated from one-dimensional values. NaN where the model is undefined (outside the
            hull of valid particles for ``"natural"``, a column without valid particles).
        """
        x, y = _as_points(x_px, y_px, ("x_px", "y_px"))
        finite = np.isfinite(x) & np.isfinite(y)
        field_to_disk(x[finite], y[finite], field_shape=self.field_shape)
        if columns is not None:
            cols = check_array("columns", columns, ndim=(0, 1, 2), dtype_kind="iu")
            shape_out = np.shape(np.atleast_1d(cols))
            cols = np.atleast_1d(cols).reshape(shape_out[0], -1)
            if shape_out[0] != x.size:
                raise ValueError(
                    f"Expected `columns` to have {x.size} rows (one per point), got shape "
                    f"{shape_out}."
                )
            bad = (cols < 0) | (cols >= self.n_columns)
            if np.any(bad):
                raise ValueError(
                    f"Expected `columns` in [0, {self.n_columns - 1}], got {cols[bad][0]}."
                )
            out = np.full(cols.shape, np.nan)
        else:
            cols = None
            out = np.full((x.size, self.n_columns), np.nan)
        idx = np.flatnonzero(finite)
        if self.kind == "zernike":
            self._eval_zernike(x, y, idx, cols, out, design)
        elif design is not None:
            raise TypeError(f"`design` applies to Zernike models only, not {self.kind!r}.")
        elif cols is None:
            self._eval_interpolant(x, y, idx, None, out)
        else:
            for k in range(cols.shape[1]):
                self._eval_interpolant(x, y, idx, cols[:, k], out[:, k])
        if cols is not None:
            return out.reshape(shape_out)
        return out[:, 0] if self.options["squeeze"] else out

    def _eval_zernike(self, x, y, idx, cols, out, design) -> None:
        p = max(int(self.n_terms_effective.max(initial=0)), 1)
        coef = self.coefficients[:p]
        if design is not None:
            design = check_array("design", design, ndim=2, dtype_kind="f", allow_empty=True)
            if design.shape[0] != x.size or design.shape[1] < p:
                raise ValueError(
                    f"Expected `design` to have shape ({x.size}, >= {p}), got {design.shape}."
                )
        coef_rows = None if cols is None else np.ascontiguousarray(coef.T)  # gathered by column
        for start in range(0, idx.size, _CHUNK):
            sel = idx[start : start + _CHUNK]
            if design is None:
                block = zernike_design(x[sel], y[sel], field_shape=self.field_shape, n_terms=p)
            else:
                block = design[sel, :p]
            if cols is None:
                out[sel] = block @ coef
            else:
                out[sel] = np.einsum("ij,ikj->ik", block, coef_rows[cols[sel]])

    def _eval_interpolant(self, x, y, idx, cols, out) -> None:
        queries = np.column_stack([x, y])
        for k, pattern in enumerate(self._patterns):
            in_pattern = np.flatnonzero(self._pattern_of == k)
            sel = idx if cols is None else idx[self._pattern_of[cols[idx]] == k]
            rows = np.flatnonzero(pattern)
            if sel.size == 0 or rows.size == 0:
                continue
            points = np.column_stack([self.x_px[rows], self.y_px[rows]])
            pi, pj, w, ok = _WEIGHTS[self.kind](points, queries[sel])
            if cols is None:
                weights = csr_matrix((w, (pi, pj)), shape=(sel.size, rows.size))
                block = weights @ self.values[np.ix_(rows, in_pattern)]
                block[~ok] = np.nan
                out[np.ix_(sel, in_pattern)] = block
            else:
                contrib = w * self.values[rows[pj], cols[sel][pi]]
                res = np.bincount(pi, contrib, minlength=sel.size).astype(np.float64)
                res[~ok] = np.nan
                out[sel] = res

    # ---------------------------------------------------------------- errors
    def residuals(self) -> np.ndarray:
        """Error estimate at each particle: ``value - prediction`` (same units as the values).

        For ``"zernike"`` the prediction is the fit itself (the residual of the least squares);
        for the interpolants it is leave-one-out: the model of all *other* valid particles of
        the column, evaluated at the particle.

        Returns
        -------
        ndarray (n, m), or (n,) for one-dimensional values
            NaN where a particle is not valid or its prediction is undefined (a particle on the
            convex hull for ``"natural"``).
        """
        if self.kind == "zernike":
            design = zernike_design(
                self.x_px,
                self.y_px,
                field_shape=self.field_shape,
                n_terms=self.coefficients.shape[0],
            )
            pred = design @ self.coefficients
        else:
            pred = np.full(self.values.shape, np.nan)
            for k, pattern in enumerate(self._patterns):
                rows = np.flatnonzero(pattern)
                in_pattern = np.flatnonzero(self._pattern_of == k)
                points = np.column_stack([self.x_px[rows], self.y_px[rows]])
                pi, pj, w, ok = _LOO[self.kind](points)
                weights = csr_matrix((w, (pi, pj)), shape=(rows.size, rows.size))
                block = weights @ self.values[np.ix_(rows, in_pattern)]
                block[~ok] = np.nan
                pred[np.ix_(rows, in_pattern)] = block
        resid = np.where(self.valid, self.values - pred, np.nan)
        return resid[:, 0] if self.options["squeeze"] else resid

    # ---------------------------------------------------------------- serialisation
    def as_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Plain arrays and an options dict (str, int, float, bool, lists), e.g. for HDF5.

        :meth:`from_arrays` rebuilds a model whose evaluation is bit-identical.
        """
        arrays = {"x_px": self.x_px, "y_px": self.y_px, "values": self.values, "valid": self.valid}
        if self.kind == "zernike":
            arrays["coefficients"] = self.coefficients
            arrays["n_terms_effective"] = self.n_terms_effective
            arrays["condition"] = self.condition
        options = dict(self.options, kind=self.kind, field_shape=list(self.field_shape))
        options["format"] = _FORMAT
        return {k: np.array(v) for k, v in arrays.items()}, options

    @classmethod
    def from_arrays(cls, arrays: dict[str, Any], options: dict[str, Any]) -> FieldModel:
        """Rebuild a model from :meth:`as_arrays` output, without refitting."""
        options = dict(options)
        fmt = options.pop("format", None)
        if fmt != _FORMAT:
            raise ValueError(f"Unsupported field-model format {fmt!r}; expected {_FORMAT}.")
        kind = check_choice("kind", options.pop("kind", None), FIELD_MODEL_KINDS)
        field_shape = tuple(int(v) for v in options.pop("field_shape", ()))
        need = ["x_px", "y_px", "values", "valid"]
        if kind == "zernike":
            need += ["coefficients", "n_terms_effective", "condition"]
        missing = [k for k in need if k not in arrays]
        if missing:
            raise ValueError(f"Field-model arrays are missing {', '.join(missing)}.")
        a = {k: np.array(arrays[k]) for k in need}
        n, m = a["values"].shape if a["values"].ndim == 2 else (-1, -1)
        if a["x_px"].shape != (n,) or a["y_px"].shape != (n,) or a["valid"].shape != (n, m):
            raise ValueError("Field-model arrays have inconsistent shapes.")
        if kind == "zernike" and (
            a["coefficients"].ndim != 2
            or a["coefficients"].shape[1] != m
            or a["n_terms_effective"].shape != (m,)
        ):
            raise ValueError("Field-model Zernike arrays have inconsistent shapes.")
        field_to_disk(np.zeros(0), np.zeros(0), field_shape=field_shape)  # checks the shape
        return cls(
            kind,
            a.pop("x_px"),
            a.pop("y_px"),
            a.pop("values"),
            a.pop("valid").astype(bool),
            field_shape,
            options,
            **a,
        )


_ZOPTS = ("n_terms", "points_per_term", "max_condition")


def _fit_zernike(x, y, values, valid, field_shape, *, n_terms, points_per_term, max_condition):
    """Least-squares Zernike coefficients, one factorisation per distinct validity pattern."""
    m = values.shape[1]
    design = zernike_design(x, y, field_shape=field_shape, n_terms=n_terms)
    coef = np.zeros((n_terms, m))
    n_eff = np.zeros(m, dtype=np.int64)
    condition = np.full(m, np.nan)
    patterns, inverse = np.unique(valid.T, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    reduced = []
    for k, pattern in enumerate(patterns):
        cols = np.flatnonzero(inverse == k)
        rows = np.flatnonzero(pattern)
        operator, cond, p = truncated_lstsq_operator(
            design[rows],
            max_terms=min(n_terms, int(rows.size // points_per_term)),
            max_condition=max_condition,
        )
        if p < n_terms:
            reduced.append((cols.size, p))
        if p < 1:
            coef[:, cols] = np.nan
            continue
        coef[:p, cols] = operator @ values[np.ix_(rows, cols)]
        n_eff[cols] = p
        condition[cols] = cond
    if reduced:
        n_cols = sum(c for c, _ in reduced)
        low = min(p for _, p in reduced)
        warnings.warn(
            f"Zernike field model: {n_cols} of {m} column(s) use fewer than n_terms = {n_terms} "
            f"terms (down to {low}), because they have fewer than points_per_term = "
            f"{points_per_term} valid particles per term or a condition number above "
            f"max_condition = {max_condition:.3g}. Columns with 0 terms are NaN.",
            UserWarning,
            stacklevel=3,
        )
    return {"coefficients": coef, "n_terms_effective": n_eff, "condition": condition}


def field_errors(model: FieldModel, *, circle_radius_px: float | None = None) -> pd.DataFrame:
    """Widefield calibration errors per column: RMS and excess kurtosis of the residuals.

    Uses :meth:`FieldModel.residuals` (Zernike fit residuals, or leave-one-out for the
    interpolants), for all particles of the square field and for those within a circle about the
    field's centre (paper Fig. 5: the experiment's particles lie within a circular subset).

    Parameters
    ----------
    model : FieldModel
    circle_radius_px : float, optional
        Radius of the circular subset, pixels; default half the shorter side of the field.

    Returns
    -------
    pandas.DataFrame
        One row per column: ``column``, then for ``region`` in ``square`` and ``circle``:
        ``n_<region>`` (particles with a finite error), ``rms_<region>`` (root mean square,
        including any mean, units of the values), ``kurtosis_<region>`` (excess kurtosis,
        Fisher's definition, ``scipy.stats.kurtosis``) and ``kurtosis_err_<region>`` (its
        standard error for a normal sample, ``sqrt(24 n (n-1)^2 / ((n-3)(n-2)(n+3)(n+5)))``).
        Statistics of fewer than 4 particles are NaN.
    """
    if not isinstance(model, FieldModel):
        raise TypeError(f"Expected `model` to be a FieldModel, got {type(model).__name__}.")
    h, w = model.field_shape
    radius = min(h, w) / 2.0 if circle_radius_px is None else circle_radius_px
    radius = check_positive("circle_radius_px", radius)
    resid = model.residuals().reshape(model.n_particles, -1)
    r = np.hypot(model.x_px - (w - 1) / 2.0, model.y_px - (h - 1) / 2.0)
    table: dict[str, Any] = {"column": np.arange(model.n_columns)}
    for region, rows in (("square", np.ones_like(r, bool)), ("circle", r <= radius)):
        sub = resid[rows]
        n = np.sum(np.isfinite(sub), axis=0)
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            rms = np.sqrt(np.nanmean(sub**2, axis=0)) if sub.size else np.full(len(n), np.nan)
            kurt = np.array([_kurtosis(col[np.isfinite(col)]) for col in sub.T])
            nf = n.astype(float)
            se = np.sqrt(24 * nf * (nf - 1) ** 2 / ((nf - 3) * (nf - 2) * (nf + 3) * (nf + 5)))
        few = n < 4
        table[f"n_{region}"] = n
        table[f"rms_{region}"] = np.where(n > 0, rms, np.nan)
        table[f"kurtosis_{region}"] = np.where(few, np.nan, kurt)
        table[f"kurtosis_err_{region}"] = np.where(few, np.nan, se)
    return pd.DataFrame(table)


def _kurtosis(sample: np.ndarray) -> float:
    return float(kurtosis(sample, fisher=True)) if sample.size >= 4 else np.nan

"""Field models: a quantity known at calibration particles, as a function of field position.

The widefield calibration (Supp. Table 2, Fig. 4) turns values known at the
calibration particles (z for a shape value, or Delta x', Delta y' for a z) into functions of the
lateral position. The paper compares three models, all behind one interface here:

``"zernike"``
    Least-squares fit of leading Noll Zernike polynomials (at most ``n_terms``, the paper's 400)
    on the disk that circumscribes the field (:mod:`latentz._shared.zernike`); by default the
    number of
    terms minimises the leave-one-out error. The paper's error estimate is the fit residual at
    each particle; the leave-one-out residual is available too, and is the honest one.
``"natural"``
    Natural-neighbour (Sibson) interpolation; NaN outside the convex hull of the valid particles,
    never extrapolated. Error estimate: leave-one-out. The weights are computed here, vectorised
    over points, and tested against MetPy's ``natural_neighbor_to_points``, which loops in Python
    and took about 0.5 ms per point (50 s for 10^5 points, per validity pattern).
``"curves"``
    Natural-neighbour interpolation valid over the whole field: inside the convex hull of the
    valid particles it is ``"natural"``; a point outside takes the Sibson coordinates of the
    nearest point of the hull (constant along the hull's normal). Error estimate: leave-one-out.
    The widefield model of this kind (:class:`~latentz.calibration.widefield.CurveModel`) uses
    these weights for Δx', Δy' and the z range; its z comes from a thin-plate spline of the
    particles' whole shape curves.
``"nearest"``
    The value of the nearest valid particle (``scipy.spatial.cKDTree``). Leave-one-out errors.

One model holds ``m`` columns at once (for example one per tabulated shape value), each with its
own set of valid particles. All are linear in the values, so the work that depends only on
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
from scipy.sparse import csr_matrix
from scipy.spatial import Delaunay, QhullError, cKDTree
from scipy.stats import kurtosis

from latentz._shared.threads import one_blas_thread
from latentz._shared.validate import check_array, check_choice, check_int, check_positive
from latentz._shared.zernike import (
    field_to_disk,
    press_terms,
    truncated_lstsq_operator,
    zernike_design,
)

__all__ = ["FieldModel", "FIELD_MODEL_KINDS", "field_errors", "field_weights"]

FIELD_MODEL_KINDS = ("zernike", "natural", "curves", "nearest")
_FORMAT = 1  # version of the representation returned by FieldModel.as_arrays
_CHUNK = 8192  # query points per block


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


def _circumcenter(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Circumcentres (k, 2) of triangles with vertices ``a``, ``b``, ``c`` (k, 2)."""
    bx, by = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    cx, cy = c[:, 0] - a[:, 0], c[:, 1] - a[:, 1]
    d = 2.0 * (bx * cy - by * cx)
    b2, c2 = bx * bx + by * by, cx * cx + cy * cy
    return np.column_stack([a[:, 0] + (cy * b2 - by * c2) / d, a[:, 1] + (bx * c2 - cx * b2) / d])


def _signed_area(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return 0.5 * (
        (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    )


def _sorted_unique(a: np.ndarray) -> np.ndarray:
    a = np.sort(a)
    return a[np.r_[True, a[1:] != a[:-1]]] if a.size else a


def _conflicts(tri, centres, radii2, queries, start):
    """All (query, triangle) pairs whose circumcircle strictly contains the query.

    A breadth-first search over triangle neighbours from the triangle containing each query
    (Bowyer-Watson's cavity, which is connected), for all queries at once.
    """
    n_tri = len(tri.simplices)
    fq, ft = np.flatnonzero(start >= 0), start[start >= 0]
    seen = np.sort(fq * n_tri + ft)
    found_q, found_t = [fq], [ft]
    while fq.size:
        cq, ct = np.repeat(fq, 3), tri.neighbors[ft].ravel()
        cq, ct = cq[ct >= 0], ct[ct >= 0]
        inside = np.sum((queries[cq] - centres[ct]) ** 2, axis=1) < radii2[ct]
        code = _sorted_unique(cq[inside] * n_tri + ct[inside])
        pos = np.minimum(np.searchsorted(seen, code), max(seen.size - 1, 0))
        code = code[seen[pos] != code] if seen.size else code
        seen = np.sort(np.concatenate([seen, code]))
        fq, ft = code // n_tri, code % n_tri
        found_q.append(fq)
        found_t.append(ft)
    return np.concatenate(found_q), np.concatenate(found_t)


def _delaunay(points: np.ndarray) -> Delaunay:
    """The Delaunay triangulation of ``points`` (n, 2) with its barycentric transforms, which
    ``find_simplex`` needs, computed at once on one BLAS thread."""
    tri = Delaunay(points)
    with one_blas_thread():
        tri.transform  # noqa: B018 (computed and cached on first access)
    return tri


def _natural_weights(points: np.ndarray, queries: np.ndarray, tri: Delaunay | None = None):
    """Sibson (natural-neighbour) coordinates of queries, by Watson's signed decomposition.

    Inserting a query ``q`` into the Delaunay triangulation removes the triangles whose
    circumcircle contains ``q``; the area its new Voronoi cell takes from particle ``a`` is the
    sum, over those triangles ``(a, b, c)`` (counter-clockwise) with circumcentre ``C``, of the
    signed areas of ``(C, cc(q, a, b), cc(q, c, a))`` (``cc``: circumcentre), because consecutive
    terms meet on Voronoi edges of ``a``. Normalised, these areas are Sibson's coordinates
    (Watson, Comput. Geosci. 18, 1992; Sibson, 1981). Outside the convex hull the interpolant is
    undefined; at a particle it is that particle's value. Checked against MetPy's
    ``natural_neighbor_to_points`` in the tests. ``tri``: the points' :func:`_delaunay`, if
    already made.
    """
    n_q = len(queries)
    none = (np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(n_q, dtype=bool))
    if len(points) < 3:
        return none
    try:
        tri = _delaunay(points) if tri is None else tri
    except QhullError:  # all particles on a line: no triangle, no interpolant
        return none
    start = tri.find_simplex(queries) if n_q else np.zeros(0, int)
    ok = start >= 0
    dist, near = cKDTree(points).query(queries)
    at_site = ok & (dist <= 1e-9 * max(float(np.ptp(points)), 1.0))
    verts = tri.simplices.copy()
    corner = points[verts]
    clockwise = _signed_area(corner[:, 0], corner[:, 1], corner[:, 2]) < 0
    verts[clockwise] = verts[clockwise][:, [0, 2, 1]]
    corner = points[verts]
    centres = _circumcenter(corner[:, 0], corner[:, 1], corner[:, 2])
    radii2 = np.sum((corner[:, 0] - centres) ** 2, axis=1)
    cq, ct = _conflicts(tri, centres, radii2, queries, np.where(at_site, -1, start))
    q, v = queries[cq], verts[ct]
    p0, p1, p2 = points[v[:, 0]], points[v[:, 1]], points[v[:, 2]]
    g01, g12, g20 = _circumcenter(q, p0, p1), _circumcenter(q, p1, p2), _circumcenter(q, p2, p0)
    centre = centres[ct]
    area = np.column_stack(
        [
            _signed_area(centre, g01, g20),
            _signed_area(centre, g12, g01),
            _signed_area(centre, g20, g12),
        ]
    )
    # Sum the areas per (query, particle) pair, then normalise per query.
    key = np.repeat(cq, 3).astype(np.int64) * len(points) + v.ravel()
    order = np.argsort(key, kind="stable")
    first = np.r_[True, key[order][1:] != key[order][:-1]] if key.size else np.zeros(0, bool)
    group = np.empty(key.size, dtype=np.int64)
    group[order] = np.cumsum(first) - 1
    unique_key = key[order][first]
    weight = np.bincount(group, area.ravel(), minlength=unique_key.size)
    kq, kp = unique_key // len(points), unique_key % len(points)
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = weight / np.bincount(kq, weight, minlength=n_q)[kq]
    bad = np.unique(kq[~np.isfinite(weight)])  # a query exactly on a Delaunay edge
    ok[bad] = False
    keep = ~np.isin(kq, bad)
    site = np.flatnonzero(at_site)
    return (
        np.concatenate([kq[keep], site]),
        np.concatenate([kp[keep], near[site]]),
        np.concatenate([weight[keep], np.ones(site.size)]),
        ok,
    )


def _onto_hull(points: np.ndarray, queries: np.ndarray, tri: Delaunay) -> np.ndarray:
    """``queries`` with those outside the convex hull of ``points`` moved to the nearest point
    of the hull, then 10⁻³ of the way towards the particles' centroid (strictly inside)."""
    outside = tri.find_simplex(queries) < 0
    if not outside.any():
        return queries
    q = queries[outside]
    a, b = points[tri.convex_hull[:, 0]], points[tri.convex_hull[:, 1]]
    ab = b - a
    t = np.einsum("qej,ej->qe", q[:, None, :] - a, ab) / np.sum(ab**2, axis=1)
    foot = a + np.clip(t, 0.0, 1.0)[:, :, None] * ab  # (queries, hull edges, 2)
    best = np.argmin(np.sum((q[:, None, :] - foot) ** 2, axis=2), axis=1)
    foot = foot[np.arange(q.shape[0]), best]
    moved = queries.copy()
    moved[outside] = foot + 1e-3 * (points.mean(axis=0) - foot)
    return moved


def _curves_weights(points: np.ndarray, queries: np.ndarray):
    """Sibson coordinates inside the convex hull, those of the nearest hull point outside it
    (the nearest particle where there is no hull: fewer than 3 particles, or all collinear)."""
    if len(points) >= 3 and len(queries):
        try:
            tri = _delaunay(points)
        except QhullError:
            tri = None
        if tri is not None:
            pi, pj, w, ok = _natural_weights(points, _onto_hull(points, queries, tri), tri)
            if ok.all():
                return pi, pj, w, ok
            # a point exactly on a Delaunay edge: its nearest particle
            k, idx, one, _ = _nearest_weights(points, queries[~ok])
            keep = ok[pi]
            pi = np.concatenate([pi[keep], np.flatnonzero(~ok)[k]])
            pj, w = np.concatenate([pj[keep], idx]), np.concatenate([w[keep], one])
            return pi, pj, w, np.ones(len(queries), dtype=bool)
    return _nearest_weights(points, queries)


def field_weights(points: np.ndarray, queries: np.ndarray, kind: str = "curves"):
    """Interpolation weights of ``kind`` ("natural", "curves" or "nearest") at ``queries``
    (k, 2) from the particles at ``points`` (n, 2): ``(query, particle, weight)`` triplets and
    a bool (k,) of the queries where the interpolant is defined. The prediction at query ``i``
    is ``sum(weight * value[particle])`` over its triplets; the weights of a query sum to 1."""
    return _WEIGHTS[check_choice("kind", kind, tuple(_WEIGHTS))](points, queries)


def _natural_loo(points: np.ndarray, weights=_natural_weights):
    """Leave-one-out Sibson weights: particle ``i`` predicted from all the others.

    Removing ``i`` changes the triangulation only in its star, and its interpolant at ``x_i``
    depends only on triangles with vertices among its neighbours and their neighbours. So
    particles more than two Delaunay edges apart can be left out together: the particles are
    coloured greedily so that no two within two edges share a colour, and each colour needs one
    triangulation.
    """
    n = len(points)
    none = (np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(n, dtype=bool))
    if n < 4:
        return none
    try:
        indptr, nbr = Delaunay(points).vertex_neighbor_vertices
    except QhullError:
        return none
    colour = np.full(n, -1)
    for i in range(n):
        ring = nbr[indptr[i] : indptr[i + 1]]
        near = np.concatenate([ring] + [nbr[indptr[j] : indptr[j + 1]] for j in ring])
        taken = set(colour[near].tolist())
        colour[i] = next(c for c in range(n) if c not in taken)
    ki, kj, kw = [], [], []
    ok = np.zeros(n, dtype=bool)
    for c in range(colour.max() + 1):
        out = np.flatnonzero(colour == c)
        rest = np.flatnonzero(colour != c)
        pi, pj, w, inside = weights(points[rest], points[out])
        ok[out] = inside
        ki.append(out[pi])
        kj.append(rest[pj])
        kw.append(w)
    return np.concatenate(ki), np.concatenate(kj), np.concatenate(kw), ok


def _nearest_loo(points: np.ndarray):
    n = len(points)
    if n < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(n, dtype=bool)
    _, idx = cKDTree(points).query(points, k=2)
    other = np.where(idx[:, 0] == np.arange(n), idx[:, 1], idx[:, 0])
    return np.arange(n), other, np.ones(n), np.ones(n, dtype=bool)


def _curves_loo(points: np.ndarray):
    return _natural_loo(points, _curves_weights)


_WEIGHTS = {"natural": _natural_weights, "curves": _curves_weights, "nearest": _nearest_weights}
_LOO = {"natural": _natural_loo, "curves": _curves_loo, "nearest": _nearest_loo}


# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FieldModel:
    """``m`` scalar fields over the image field, each known at a subset of particles.

    Build with :meth:`FieldModel.from_estimate`; evaluate by calling; :meth:`residuals` gives the
    error estimate at each particle; :meth:`as_arrays` / :meth:`from_arrays` serialise.

    Attributes
    ----------
    kind : str
        ``"zernike"``, ``"natural"``, ``"curves"`` or ``"nearest"``.
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
        term_selection: str = "press",
    ) -> FieldModel:
        """Build a field model from values at particle positions.

        Parameters
        ----------
        x_px, y_px : ndarray (n,)
            Particle positions in pixels, inside the field and all distinct.
        values : ndarray (n,) or (n, m)
            Values at the particles, any unit; ``m`` columns are modelled independently.
        kind : {"zernike", "natural", "curves", "nearest"}
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
        term_selection : {"press", "max"}
            Zernike only. ``"max"`` (the paper's practice) uses all the terms that
            ``points_per_term`` allows; ``"press"`` uses the complete radial orders, up to that,
            that minimise the leave-one-out error (PRESS), summed over the columns that share a
            validity pattern. With the sparse, random sampling of calibration particles, high
            orders fit the particles ever better while oscillating wildly between them and in
            the corners of the square field (for 500 particles and 250 terms the error between
            particles was ~700x the fit residual), which only leave-one-out reveals.
        max_condition : float
            Zernike only. The column then uses the largest number of leading (Noll-ordered) of
            those terms whose design matrix has a condition number <= ``max_condition``. A
            column left with no term is NaN. Reductions by ``points_per_term`` (with
            ``"max"``) or by ``max_condition`` are reported by one ``UserWarning``;
            :attr:`n_terms_effective` gives the terms used.

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
            options["term_selection"] = check_choice(
                "term_selection", term_selection, ("press", "max")
            )
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
        self,
        x_px: Any,
        y_px: Any,
        *,
        columns: Any = None,
        design: np.ndarray | None = None,
        weights: dict | None = None,
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
        weights : dict, optional
            Interpolants only (Zernike models ignore it): the neighbour weights computed here,
            by particles and query points, shared by several models evaluated at the same
            points (the weights of a set of particles at a set of points are computed once).

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
        else:
            self._eval_interpolant(x, y, idx, cols, out, {} if weights is None else weights)
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

    def _eval_interpolant(self, x, y, idx, cols, out, weights: dict) -> None:
        """Fill ``out`` at points ``idx``: every column (``cols`` None) or, per point, the
        columns ``cols[i, :]``. The weights of each validity pattern are computed once, for
        every point that needs that pattern in any of its columns, and kept in ``weights``
        (:meth:`__call__`); a pattern that none of ``cols`` reads is skipped."""
        queries = np.column_stack([x, y])
        read = np.arange(len(self._patterns))
        if cols is not None:
            read = np.unique(self._pattern_of[cols[idx]])
        for k in read:
            rows = np.flatnonzero(self._patterns[k])
            uses = None if cols is None else self._pattern_of[cols[idx]] == k  # (points, k)
            sel = idx if cols is None else idx[uses.any(axis=1)]
            if sel.size == 0 or rows.size == 0:
                continue
            points = np.column_stack([self.x_px[rows], self.y_px[rows]])
            key = (self.kind, points.tobytes(), queries[sel].tobytes())
            if key not in weights:
                weights[key] = _WEIGHTS[self.kind](points, queries[sel])
            pi, pj, w, ok = weights[key]
            if cols is None:
                in_pattern = np.flatnonzero(self._pattern_of == k)
                matrix = csr_matrix((w, (pi, pj)), shape=(sel.size, rows.size))
                block = matrix @ self.values[np.ix_(rows, in_pattern)]
                block[~ok] = np.nan
                out[np.ix_(sel, in_pattern)] = block
                continue
            for c in range(cols.shape[1]):
                here = self._pattern_of[cols[sel, c]] == k
                entry = here[pi]
                contrib = w[entry] * self.values[rows[pj[entry]], cols[sel[pi[entry]], c]]
                res = np.bincount(pi[entry], contrib, minlength=sel.size).astype(np.float64)
                res[~ok] = np.nan
                out[sel[here], c] = res[here]

    # ---------------------------------------------------------------- errors
    def residuals(self, *, leave_one_out: bool | None = None) -> np.ndarray:
        """Error estimate at each particle: ``value - prediction`` (same units as the values).

        Parameters
        ----------
        leave_one_out : bool, optional
            If True, the prediction at a particle comes from the model of all *other* valid
            particles of its column. For the interpolants this is the only meaningful choice
            (and the default). For ``"zernike"`` the default (False) is the paper's: the fit
            residual itself, which shrinks as terms are added even while the model worsens
            between particles; True gives the leave-one-out residual ``r_i / (1 - h_ii)``
            (leverage ``h_ii``), an honest estimate of the error away from the particles.

        Returns
        -------
        ndarray (n, m), or (n,) for one-dimensional values
            NaN where a particle is not valid or its prediction is undefined (a particle on the
            convex hull for ``"natural"``).
        """
        if self.kind != "zernike" and leave_one_out is False:
            raise ValueError(
                f"Interpolants reproduce their data; `leave_one_out` must be True for "
                f"{self.kind!r}, got False."
            )
        if self.kind == "zernike":
            p = max(int(self.n_terms_effective.max(initial=0)), 1)
            design = zernike_design(self.x_px, self.y_px, field_shape=self.field_shape, n_terms=p)
            pred = design @ self.coefficients[:p]
            if leave_one_out:
                scale = np.full(self.values.shape, np.nan)
                for k, pattern in enumerate(self._patterns):
                    rows = np.flatnonzero(pattern)
                    cols = np.flatnonzero(self._pattern_of == k)
                    n_eff = int(self.n_terms_effective[cols[0]])
                    if n_eff == 0:
                        continue
                    q = np.linalg.qr(design[rows, :n_eff])[0]
                    with np.errstate(divide="ignore"):
                        scale[np.ix_(rows, cols)] = (1.0 / (1.0 - np.sum(q**2, axis=1)))[:, None]
                pred = self.values - (self.values - pred) * scale
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


_ZOPTS = ("n_terms", "points_per_term", "max_condition", "term_selection")


def _fit_zernike(
    x, y, values, valid, field_shape, *, n_terms, points_per_term, max_condition, term_selection
):
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
        wanted = min(n_terms, int(rows.size // points_per_term))
        if term_selection == "press":
            wanted = press_terms(design[rows], values[np.ix_(rows, cols)], max_terms=wanted)
        operator, cond, p = truncated_lstsq_operator(
            design[rows], max_terms=wanted, max_condition=max_condition
        )
        if p < (wanted if term_selection == "press" else n_terms) or p == 0:
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
            f"Zernike field model: {n_cols} of {m} column(s) use fewer terms than "
            f"{'selected' if term_selection == 'press' else f'n_terms = {n_terms}'} "
            f"(down to {low}), because they have fewer than points_per_term = "
            f"{points_per_term} valid particles per term or a condition number above "
            f"max_condition = {max_condition:.3g}. Columns with 0 terms are NaN.",
            UserWarning,
            stacklevel=3,
        )
    return {"coefficients": coef, "n_terms_effective": n_eff, "condition": condition}


def field_errors(
    model: FieldModel,
    *,
    circle_radius_px: float | None = None,
    leave_one_out: bool | None = None,
    residuals: np.ndarray | None = None,
) -> pd.DataFrame:
    """Widefield calibration errors per column: RMS and excess kurtosis of the residuals.

    Uses :meth:`FieldModel.residuals` (Zernike fit residuals, or leave-one-out for the
    interpolants), for all particles of the square field and for those within a circle about the
    field's centre (paper Fig. 5: the experiment's particles lie within a circular subset).

    Parameters
    ----------
    model : FieldModel
    circle_radius_px : float, optional
        Radius of the circular subset, pixels; default half the shorter side of the field.
    leave_one_out : bool, optional
        Passed to :meth:`FieldModel.residuals`; True gives honest Zernike errors.
    residuals : ndarray (n, m), optional
        ``model.residuals(leave_one_out=...)`` if already computed.

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
    if residuals is None:
        residuals = model.residuals(leave_one_out=leave_one_out)
    resid = np.asarray(residuals).reshape(model.n_particles, -1)
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

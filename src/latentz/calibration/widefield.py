"""Widefield models: z(x', y'; s) and Δx', Δy'(x', y'; z) over the whole field (Fig. 4).

Each calibration particle gives z for a shape value s (its inverse function, inside its monotonic
range) and Δx'(z), Δy'(z). A :class:`~latentz.calibration.fieldmodels.FieldModel` turns those values
into functions of field position. To localize many spots without a least-squares problem per
spot, the values are tabulated on fine grids of s and z (one field-model column per grid value;
the work that depends only on which particles are valid is shared by the columns with the same
validity pattern), and each spot interpolates linearly between the two columns around its s
(then its z).

Range: a spot is in range only if, among its ``k_near`` nearest calibration particles, at least
``min_fraction`` cover its s (both tabulated columns around it); otherwise z is NaN and
``in_range`` False. Nothing is extrapolated.

:class:`CurveModel` (``field_model="curves"``) carries each particle's whole measured shape curve
across the field instead. The curves, sampled on one fine z grid, are interpolated over the
field by a thin-plate spline, column by column, with the smoothing that predicts each particle
best from the others (leave-one-out): exact where aberrations change between neighbouring
particles, smooth where the field is smoother than the particles' own scatter (their size and
height). At a spot's position that gives its own curve s(z), which is inverted where it crosses
the spot's s, inside the mean of its natural neighbours' monotonic ranges. Δx', Δy' are the
Sibson-weighted mean of the natural neighbours' own Δx'(z), Δy'(z) at that z. Interpolating s at
fixed z, rather than averaging the neighbours' z at fixed s, keeps the interpolant smooth where
a curve turns fast (near focus), and the spline follows aberrations that vary on the scale of
the particle spacing, where a weighted mean of neighbours flattens them (docs/accuracy.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from latentz._shared.validate import check_array, check_int, check_positive
from latentz._shared.zernike import zernike_design
from latentz.calibration.fieldmodels import FieldModel, field_weights
from latentz.calibration.polymodel import PolyModel

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["CurveModel", "WidefieldModel", "covered_span"]

_PARTS = ("axial", "dx", "dy")  # the three field models, as named in files

#: Shape values that fewer kept particles cover are not tabulated (nor evaluated).
MIN_PARTICLES = 10


def _bracket(grid: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left column index, weight of the right column, and whether v is inside the grid."""
    inside = np.isfinite(v) & (v >= grid[0]) & (v <= grid[-1])
    j = np.clip(np.searchsorted(grid, np.where(inside, v, grid[0])) - 1, 0, grid.size - 2)
    t = (np.where(inside, v, grid[0]) - grid[j]) / (grid[j + 1] - grid[j])
    return j, t, inside


def covered_span(domain: np.ndarray, min_particles: int) -> tuple[float, float]:
    """Smallest and largest shape value inside at least ``min_particles`` of the (n, 2) ranges."""
    lo, hi = domain[:, 0], domain[:, 1]
    ok = np.isfinite(lo) & np.isfinite(hi)
    if ok.sum() < min_particles:
        raise ValueError(
            f"Only {int(ok.sum())} kept calibration particles have a monotonic shape range; "
            f"the widefield model needs at least {min_particles}."
        )
    lo, hi = lo[ok], hi[ok]
    ends = np.concatenate([lo, hi])  # the coverage count only changes at range ends
    count = np.sum((lo[:, None] <= ends) & (ends <= hi[:, None]), axis=0)
    covered = ends[count >= min_particles]
    if covered.size == 0:
        raise ValueError(
            f"No shape value is inside the ranges of {min_particles} kept calibration particles."
        )
    return float(covered.min()), float(covered.max())


def _spot_arrays(x_px: Any, y_px: Any, s: Any, iterations: int, field_shape) -> tuple:
    """x, y, s as float arrays, and which spots lie inside the calibrated field (pixel edges
    included; NaN positions are outside)."""
    x = np.atleast_1d(np.asarray(x_px, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y_px, dtype=np.float64))
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    check_int("iterations", iterations, minimum=0)
    h, w = field_shape
    with np.errstate(invalid="ignore"):
        inside = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    return x, y, s, inside


@dataclass(frozen=True, eq=False)
class WidefieldModel:
    """Tabulated widefield axial and lateral models.

    Attributes
    ----------
    s_grid : ndarray (m_s,)
        Shape values of the axial columns, increasing.
    z_grid_nm : ndarray (m_z,)
        Heights of the lateral columns (tilt-corrected nm), increasing.
    axial : FieldModel
        ``m_s`` columns: z (nm) at each particle for each ``s_grid`` value.
    dx, dy : FieldModel
        ``m_z`` columns: Δx', Δy' (pixels) for each ``z_grid_nm`` value.
    k_near : int
        Number of nearest particles checked for range.
    min_fraction : float
        Fraction of those that must cover a spot's s.
    """

    s_grid: np.ndarray
    z_grid_nm: np.ndarray
    axial: FieldModel
    dx: FieldModel
    dy: FieldModel
    k_near: int
    min_fraction: float

    @classmethod
    def from_tables(
        cls,
        x_px: np.ndarray,
        y_px: np.ndarray,
        s_grid: np.ndarray,
        z_table_nm: np.ndarray,
        z_grid_nm: np.ndarray,
        dx_table_px: np.ndarray,
        dy_table_px: np.ndarray,
        *,
        kind: str,
        field_shape: tuple[int, int],
        n_terms: int = 400,
        k_near: int = 6,
        min_fraction: float = 0.5,
    ) -> WidefieldModel:
        """Build from values tabulated at the particles.

        Parameters
        ----------
        x_px, y_px : ndarray (n,)
            Calibration particle positions in the field, pixels.
        s_grid : ndarray (m_s,)
            Increasing shape values.
        z_table_nm : ndarray (n, m_s)
            z of each particle at each s (NaN outside its range), nm.
        z_grid_nm : ndarray (m_z,)
            Increasing heights, nm.
        dx_table_px, dy_table_px : ndarray (n, m_z)
            Δx', Δy' of each particle at each z (NaN where unknown), pixels.
        kind : {"zernike", "natural", "nearest"}
        field_shape : (int, int)
        n_terms : int
            Maximum Zernike terms.
        k_near : int
            Nearest particles consulted for the range test.
        min_fraction : float
            In (0, 1]: fraction of those that must cover the spot's s.
        """
        s_grid = check_array("s_grid", s_grid, ndim=1, dtype_kind="f")
        z_grid = check_array("z_grid_nm", z_grid_nm, ndim=1, dtype_kind="f")
        for name, grid in (("s_grid", s_grid), ("z_grid_nm", z_grid)):
            if grid.size < 2 or np.any(np.diff(grid) <= 0):
                raise ValueError(f"Expected `{name}` strictly increasing with >= 2 values.")
        k_near = check_int("k_near", k_near, minimum=1)
        min_fraction = check_positive("min_fraction", min_fraction)
        if min_fraction > 1:
            raise ValueError(f"Expected `min_fraction` in (0, 1], got {min_fraction!r}.")
        opts = {"kind": kind, "field_shape": field_shape}
        if kind == "zernike":
            opts["n_terms"] = n_terms
        axial = FieldModel.from_estimate(x_px, y_px, z_table_nm, **opts)
        dx = FieldModel.from_estimate(x_px, y_px, dx_table_px, **opts)
        dy = FieldModel.from_estimate(x_px, y_px, dy_table_px, **opts)
        for name, model, grid in (("z_table_nm", axial, s_grid), ("dx_table_px", dx, z_grid)):
            if model.n_columns != grid.size:
                raise ValueError(f"Expected `{name}` to have {grid.size} columns.")
        return cls(s_grid, z_grid, axial, dx, dy, min(k_near, axial.n_particles), min_fraction)

    @classmethod
    def from_calibration(
        cls,
        cal: CalibrationView,
        *,
        kind: str,
        field_shape: tuple[int, int],
        n_terms: int = 400,
        n_s: int = 241,
        z_step_nm: float = 25.0,
        min_particles: int = MIN_PARTICLES,
        k_near: int = 6,
        min_fraction: float = 0.5,
    ) -> WidefieldModel:
        """Tabulate a :class:`~latentz.calibration.result.Calibration`'s kept particles.

        ``field_shape`` is ``(H, W)`` of the whole field in pixels (stage positions included).
        The s grid has ``n_s`` values over the shape values that at least ``min_particles`` kept
        particles cover (a few particles with unusual ranges must not stretch it), and the z grid
        spans the resulting heights in steps of at most ``z_step_nm``. Each particle contributes
        only inside its own ranges: its monotonic shape range and the z span it was imaged over
        (:meth:`~latentz.calibration.result.Calibration.local_z`, ``local_delta``). Other
        options as in :meth:`from_tables`.
        """
        kept = cal.kept
        n_s = check_int("n_s", n_s, minimum=2)
        min_particles = check_int("min_particles", min_particles, minimum=1)
        s_lo, s_hi = covered_span(
            cal.local.shapes[cal.shape].inverse.domain[kept], min(min_particles, kept.size)
        )
        s_grid = np.linspace(s_lo, s_hi, n_s)
        z_table = np.stack([cal.local_z(s)[kept] for s in s_grid], axis=1)
        if not np.isfinite(z_table).any():
            raise ValueError("No kept calibration particle gives z for any shape value.")
        z_lo, z_hi = np.nanmin(z_table), np.nanmax(z_table)
        step = check_positive("z_step_nm", z_step_nm)
        z_grid = np.linspace(z_lo, z_hi, max(2, int(np.ceil((z_hi - z_lo) / step)) + 1))
        deltas = [cal.local_delta(z) for z in z_grid]
        dx_t = np.stack([d[0][kept] for d in deltas], axis=1)
        dy_t = np.stack([d[1][kept] for d in deltas], axis=1)
        x, y = cal.positions[kept].T
        return cls.from_tables(
            x,
            y,
            s_grid,
            z_table,
            z_grid,
            dx_t,
            dy_t,
            kind=kind,
            field_shape=field_shape,
            n_terms=n_terms,
            k_near=k_near,
            min_fraction=min_fraction,
        )

    def as_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``({"name": ndarray}, JSON-able options)``; :meth:`from_arrays` rebuilds a model whose
        evaluation is bit-identical, without refitting."""
        arrays = {"s_grid": self.s_grid, "z_grid_nm": self.z_grid_nm}
        options: dict[str, Any] = {"k_near": self.k_near, "min_fraction": self.min_fraction}
        for name in _PARTS:
            part, part_options = getattr(self, name).as_arrays()
            arrays.update({f"{name}/{k}": v for k, v in part.items()})
            options[name] = part_options
        return arrays, options

    @classmethod
    def from_arrays(cls, arrays: dict[str, Any], options: dict[str, Any]) -> WidefieldModel:
        """Rebuild from :meth:`as_arrays` output; a missing part is a ``ValueError``."""
        missing = [k for k in ("s_grid", "z_grid_nm") if k not in arrays]
        missing += [k for k in (*_PARTS, "k_near", "min_fraction") if k not in options]
        if missing:
            raise ValueError(f"Widefield model arrays are missing {', '.join(missing)}.")
        parts = {
            name: FieldModel.from_arrays(
                {k[len(name) + 1 :]: v for k, v in arrays.items() if k.startswith(f"{name}/")},
                options[name],
            )
            for name in _PARTS
        }
        return cls(
            np.asarray(arrays["s_grid"], dtype=np.float64),
            np.asarray(arrays["z_grid_nm"], dtype=np.float64),
            **parts,
            k_near=int(options["k_near"]),
            min_fraction=float(options["min_fraction"]),
        )

    @property
    def s_range(self) -> tuple[float, float]:
        """Smallest and largest tabulated shape value: the span that at least ``min_particles``
        kept particles cover (:meth:`from_calibration`)."""
        return float(self.s_grid[0]), float(self.s_grid[-1])

    def coverage(self, x_px: Any, y_px: Any, s: Any) -> np.ndarray:
        """Whether enough nearby particles cover each spot's shape value (bool per spot)."""
        x, y, s = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (x_px, y_px, s))
        j, _, inside = _bracket(self.s_grid, s)
        ok = inside & np.isfinite(x) & np.isfinite(y)
        tree = cKDTree(np.column_stack([self.axial.x_px, self.axial.y_px]))
        pts = np.column_stack([np.where(ok, x, 0.0), np.where(ok, y, 0.0)])
        _, near = tree.query(pts, k=self.k_near)
        near = near.reshape(x.size, -1)
        valid = self.axial.valid
        covers = valid[near, j[:, None]] & valid[near, j[:, None] + 1]
        return ok & (covers.mean(axis=1) >= self.min_fraction)

    def _columns(self, model, grid, x, y, v, design, weights):
        j, t, inside = _bracket(grid, v)
        pair = model(x, y, columns=np.column_stack([j, j + 1]), design=design, weights=weights)
        return np.where(inside, pair[:, 0] * (1 - t) + pair[:, 1] * t, np.nan)

    def __call__(
        self, x_px: Any, y_px: Any, s: Any, *, iterations: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """z (nm), Δx', Δy' (pixels) and in_range for spots at apparent (x', y') with shape s.

        ``iterations`` > 0 re-evaluates z at the laterally corrected position (x' − Δx',
        y' − Δy') that many times (Supp. Note 1).
        """
        x, y, s, inside = _spot_arrays(x_px, y_px, s, iterations, self.axial.field_shape)
        if x.size == 0:
            empty = np.empty(0)
            return empty, empty, empty, np.zeros(0, dtype=bool)
        x, y = np.where(inside, x, np.nan), np.where(inside, y, np.nan)  # beyond: out of range
        in_range = self.coverage(x, y, s)
        xq, yq = np.where(in_range, x, np.nan), np.where(in_range, y, np.nan)
        weights = {}  # the interpolants' neighbour weights, shared by the three models
        for it in range(iterations + 1):
            design = self._design(xq, yq)
            z = self._columns(self.axial, self.s_grid, xq, yq, s, design, weights)
            if it:
                design = self._design(x, y)
            dx = self._columns(self.dx, self.z_grid_nm, x, y, z, design, weights)
            dy = self._columns(self.dy, self.z_grid_nm, x, y, z, design, weights)
            xq, yq = x - dx, y - dy
        in_range &= np.isfinite(z) & np.isfinite(dx) & np.isfinite(dy)
        nan = np.where(in_range, 0.0, np.nan)
        return z + nan, dx + nan, dy + nan, in_range

    def _design(self, x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
        if self.axial.kind != "zernike":
            return None
        p = max(int(np.max(m.n_terms_effective, initial=1)) for m in (self.axial, self.dx, self.dy))
        ok = np.isfinite(x) & np.isfinite(y)
        d = np.full((x.size, p), np.nan)
        d[ok] = zernike_design(x[ok], y[ok], field_shape=self.axial.field_shape, n_terms=p)
        return d


def _weighted_mean(
    query: np.ndarray, weight: np.ndarray, value: np.ndarray, use: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per query, the mean of ``value`` over its triplets where ``use``, weighted by ``weight``,
    and the weight those triplets carry (the query's weights sum to 1)."""
    w = np.where(use, weight, 0.0)
    total = np.bincount(query, w, minlength=n)
    summed = np.bincount(query, w * np.where(use, value, 0.0), minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return summed / total, total


#: Most grid columns of the shape surface. The grid is at the calibration's plane spacing: the
#: measured values are linear between planes, and a grid 4x finer changed z by < 1 nm on the
#: validation microscope at 4x the time.
_MAX_GRID = 1200
#: Spots per block of the shape surface's evaluation ((block, grid) arrays; the neighbour
#: weights are computed once for all spots: each call triangulates the particles).
_CHUNK = 4096


def sampled_curves(z_nm: np.ndarray, values: np.ndarray, grid_nm: np.ndarray) -> np.ndarray:
    """(n, m) each row of ``values`` (n, n_z) at heights ``z_nm`` (n, n_z) on ``grid_nm`` (m,):
    linear between its finite planes and held at its first and last beyond them (NaN rows for
    fewer than two).

    The measured values, not the order-16 forward models: near focus, where s turns fastest,
    those miss noise-free curves by several times the noise of 2e5-photon beads. The values
    held beyond a particle's planes (its span differs from the others' by the substrate's tilt)
    are never read there: z is sought only inside the particles' monotonic ranges."""
    out = np.full((values.shape[0], grid_nm.size), np.nan)
    for i, (z, v) in enumerate(zip(z_nm, values, strict=True)):
        ok = np.isfinite(z) & np.isfinite(v)
        if ok.sum() >= 2:
            order = np.argsort(z[ok])
            out[i] = np.interp(grid_nm, z[ok][order], v[ok][order])
    return out


#: Candidate smoothings of the thin-plate spline (added to the kernel's diagonal, whose entries
#: r² log r are ~10⁵-10⁷ between particles tens to hundreds of px apart).
_SMOOTHING = (0.0, *(10.0**k for k in range(9)))


def _loo_smoothing(points: np.ndarray, values: np.ndarray) -> float:
    """The smoothing of :data:`_SMOOTHING` whose thin-plate spline through ``values`` (n, m) at
    ``points`` (n, 2) px predicts each point best from the others (mean square over points and
    columns; leave-one-out residuals by Rippa's formula, c_i / (A⁻¹)_ii of the augmented system).

    Interpolating exactly (0) suits aberrations that change between neighbouring particles;
    smoothing suits a field smoother than the particles' own scatter (their size, their height
    on the substrate), which an exact interpolant passes through at every particle.
    """
    n = len(points)
    r = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        kernel = np.where(r > 0, r**2 * np.log(r), 0.0)
    poly = np.column_stack([np.ones(n), points - points.mean(axis=0)])
    system = np.block([[kernel, poly], [poly.T, np.zeros((3, 3))]])
    best, best_err = 0.0, np.inf
    for smoothing in _SMOOTHING:
        system[np.arange(n), np.arange(n)] = smoothing
        try:
            inverse = np.linalg.inv(system)
        except np.linalg.LinAlgError:
            continue
        coef = inverse[:n, :n] @ values
        err = float(np.mean((coef / np.diag(inverse)[:n, None]) ** 2))
        if err < best_err:
            best, best_err = smoothing, err
    return best


def _spline(points: np.ndarray, values: np.ndarray, smoothing: float) -> RBFInterpolator:
    """Thin-plate spline through ``values`` (n, m) at ``points`` (n, 2) px with ``smoothing``;
    with fewer than three points, or all on one line, the linear radial basis with a constant."""
    try:
        return RBFInterpolator(points, values, kernel="thin_plate_spline", smoothing=smoothing)
    except (ValueError, np.linalg.LinAlgError):
        return RBFInterpolator(points, values, kernel="linear", degree=0)


def crossing(
    grid_nm: np.ndarray, curves: np.ndarray, s: np.ndarray, lo_nm: np.ndarray, hi_nm: np.ndarray
) -> np.ndarray:
    """Where each row of ``curves`` (k, m), linear between the columns at ``grid_nm``, equals
    ``s`` (k,) inside [``lo_nm``, ``hi_nm``] (nm; the mean where it does so more than once, NaN
    where never)."""
    d = curves - s[:, None]
    with np.errstate(invalid="ignore"):
        above = d >= 0
    row, col = np.nonzero((above[:, 1:] != above[:, :-1]) & np.isfinite(d[:, 1:] + d[:, :-1]))
    d0, d1 = d[row, col], d[row, col + 1]
    z = grid_nm[col] + d0 / (d0 - d1) * (grid_nm[col + 1] - grid_nm[col])
    keep = (z >= lo_nm[row]) & (z <= hi_nm[row])
    n = np.bincount(row[keep], minlength=s.size)
    with np.errstate(invalid="ignore"):
        return np.bincount(row[keep], z[keep], minlength=s.size) / np.where(n > 0, n, np.nan)


@dataclass(frozen=True, eq=False)
class CurveModel:
    """Widefield model that interpolates the particles' own curves (module notes).

    Attributes
    ----------
    x_px, y_px : ndarray (n,)
        Kept particle positions, pixels.
    z_grid_nm : ndarray (m,)
        Heights (tilt-corrected nm) at which the shape surface is interpolated, increasing.
    surface : RBFInterpolator
        Thin-plate spline over the field (px) of the particles' measured shape curves on
        ``z_grid_nm`` (:func:`sampled_curves`), smoothed as :func:`_loo_smoothing` chooses
        over the grid heights inside most particles' monotonic ranges.
    z_range_nm : ndarray (n, 2)
        Each particle's monotonic z range around focus: a spot's z is sought inside the
        weighted mean of its natural neighbours' ranges.
    dx, dy : PolyModel
        Each particle's Δx'(z), Δy'(z), pixels.
    z_span_nm : ndarray (n, 2)
        The z span each particle was imaged over: its curves are used only inside it.
    field_shape : (int, int)
    """

    x_px: np.ndarray
    y_px: np.ndarray
    z_grid_nm: np.ndarray
    surface: RBFInterpolator
    z_range_nm: np.ndarray
    dx: PolyModel
    dy: PolyModel
    z_span_nm: np.ndarray
    field_shape: tuple[int, int]

    @classmethod
    def from_calibration(cls, cal: CalibrationView, *, field_shape: tuple[int, int]) -> CurveModel:
        """The kept particles of a :class:`~latentz.calibration.result.Calibration`."""
        kept = cal.kept
        if kept.size == 0:
            raise ValueError("Every calibration particle was culled: nothing to apply.")
        x, y = cal.positions[kept].T
        shape = cal.local.shapes[cal.shape]
        span = cal.z_span_nm[kept]
        z = cal.local.z_nm[kept]
        lo, hi = np.nanmin(span[:, 0]), np.nanmax(span[:, 1])
        step = max(np.nanmedian(np.abs(np.diff(z, axis=1))), (hi - lo) / _MAX_GRID)
        grid = np.arange(lo, hi + step / 2, step)
        curves = sampled_curves(z, shape.values[kept], grid)
        has = np.isfinite(curves).all(axis=1)
        if not has.any():
            raise ValueError("No kept calibration particle has two planes with a shape value.")
        points, curves = np.column_stack([x, y])[has], curves[has]
        ranges = shape.z_range[kept][has]
        central = (grid >= np.nanmedian(ranges[:, 0])) & (grid <= np.nanmedian(ranges[:, 1]))
        smoothing = _loo_smoothing(points, curves[:, central]) if central.any() else 0.0
        surface = _spline(points, curves, smoothing)
        return cls(x, y, grid, surface, shape.z_range[kept],
                   cal.local.dx[kept], cal.local.dy[kept], span, tuple(field_shape))  # fmt: skip

    def _inside_span(self, particle: np.ndarray, z: np.ndarray) -> np.ndarray:
        lo, hi = self.z_span_nm[particle].T
        with np.errstate(invalid="ignore"):
            return (z >= lo) & (z <= hi)

    def __call__(
        self, x_px: Any, y_px: Any, s: Any, *, iterations: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """z (nm), Δx', Δy' (pixels) and in_range for spots at apparent (x', y') with shape s.

        ``iterations`` > 0 re-evaluates z at the laterally corrected position (x' − Δx',
        y' − Δy') that many times (Supp. Note 1).
        """
        x, y, s, inside = _spot_arrays(x_px, y_px, s, iterations, self.field_shape)
        rows = np.flatnonzero(inside & np.isfinite(s))
        out = [np.full(x.size, np.nan) for _ in range(3)]
        in_range = np.zeros(x.size, dtype=bool)
        if rows.size == 0:
            return out[0], out[1], out[2], in_range
        xr, yr, sr = x[rows], y[rows], s[rows]
        q, p, wt = self._weights(xr, yr)  # the lateral models at the apparent position
        xq, yq = xr, yr
        for it in range(iterations + 1):
            zr = self._z(xq, yq, sr, (q, p, wt) if it == 0 else self._weights(xq, yq))
            dxr, dyr = (self._delta(model, q, p, wt, zr) for model in (self.dx, self.dy))
            xq, yq = xr - dxr, yr - dyr
        in_range[rows] = np.isfinite(zr) & np.isfinite(dxr) & np.isfinite(dyr)
        for full, part in zip(out, (zr, dxr, dyr), strict=True):
            full[rows] = np.where(in_range[rows], part, np.nan)
        return out[0], out[1], out[2], in_range

    def _weights(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """(spot, particle, weight) triplets of the spots at (x, y)."""
        points = np.column_stack([self.x_px, self.y_px])
        q, p, wt, _ = field_weights(points, np.column_stack([x, y]))
        return q, p, wt

    def shape_curves(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(k, m) shape curves at (x, y) px on :attr:`z_grid_nm`."""
        return self.surface(np.column_stack([x, y]))

    def _z(self, x: np.ndarray, y: np.ndarray, s: np.ndarray, weights: tuple) -> np.ndarray:
        """z of each spot: where the shape curve at its position crosses its s, inside the
        mean of its natural neighbours' monotonic ranges (``weights``, the triplets of
        :meth:`_weights` at (x, y); NaN where it does not)."""
        q, p, wt = weights
        lo, hi = (_weighted_mean(q, wt, self.z_range_nm[p, i], np.isfinite(self.z_range_nm[p, i]),
                                 x.size)[0] for i in (0, 1))  # fmt: skip
        z = np.full(x.size, np.nan)
        for b in np.array_split(np.arange(x.size), max(1, -(-x.size // _CHUNK))):
            z[b] = crossing(self.z_grid_nm, self.shape_curves(x[b], y[b]), s[b], lo[b], hi[b])
        return z

    def _delta(self, model: PolyModel, q, p, wt, z) -> np.ndarray:
        """Δx' or Δy' of each spot: its neighbours' own curves at its z (NaN z gives NaN)."""
        zq = z[q]
        use = self._inside_span(p, zq)
        zq = np.where(use, zq, self.z_span_nm[p, 0])
        return _weighted_mean(q, wt, model[p](zq), use, z.size)[0]

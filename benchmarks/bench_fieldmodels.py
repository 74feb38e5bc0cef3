"""Benchmark: field models at the widefield calibration's scale.

Zernike: fit 400 terms to 500 particles x 2000 columns (one column per tabulated shape value),
with one validity pattern for all columns and with the realistic case of each particle covering a
contiguous run of columns (many distinct patterns); evaluate at 10^5 points, both every point in
its own column (what ``apply`` needs) and all points in a few columns. Natural and nearest
neighbour: evaluation at 10^5 points and leave-one-out residuals for all columns; MetPy's
natural-neighbour routine (the tests' reference) is timed on fewer points for comparison.
Multithreaded OpenBLAS slows the many small factorisations badly when the cores are busy;
``OPENBLAS_NUM_THREADS=1`` avoids that.
Run: ``python benchmarks/bench_fieldmodels.py [--columns N] [--particles N] [--points N]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from metpy.interpolate import natural_neighbor_to_points

from latentz._shared.zernike import zernike_design
from latentz.calibration.fieldmodels import FieldModel, field_errors

SHAPE = (512, 512)


def _timed(label: str, func, *args, **kwargs):
    start = time.perf_counter()
    out = func(*args, **kwargs)
    print(f"{label}: {time.perf_counter() - start:.2f} s")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--particles", type=int, default=500)
    parser.add_argument("--columns", type=int, default=2000)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--terms", type=int, default=400)
    parser.add_argument("--metpy-points", type=int, default=2000)
    args = parser.parse_args()
    n, m = args.particles, args.columns
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, SHAPE[1] - 1, n), rng.uniform(0, SHAPE[0] - 1, n)
    values = np.sin(x / 70)[:, None] * np.linspace(-1, 1, m) + np.cos(y / 90)[:, None]
    lo, hi = rng.integers(0, m // 5, n), rng.integers(4 * m // 5, m + 1, n)
    ranged = (np.arange(m) >= lo[:, None]) & (np.arange(m) < hi[:, None])
    n_patterns = np.unique(ranged.T, axis=0).shape[0]
    qx, qy = rng.uniform(0, SHAPE[1] - 1, args.points), rng.uniform(0, SHAPE[0] - 1, args.points)
    qcols = rng.integers(0, m, args.points)

    label = f"zernike fit, {args.terms} terms x {n} particles x {m} columns"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # term reductions are expected here
        models = {}
        for selection in ("press", "max"):
            opts = {"field_shape": SHAPE, "n_terms": args.terms, "term_selection": selection}
            for valid, what in ((None, "1 pattern"), (ranged, f"{n_patterns} patterns")):
                model = _timed(
                    f"{label}, {what}, term_selection={selection!r}",
                    FieldModel.from_estimate,
                    *(x, y, values),
                    kind="zernike",
                    valid=valid,
                    **opts,
                )
                terms, cond = model.n_terms_effective, np.nanmax(model.condition)
                print(f"  effective terms {terms.min()}-{terms.max()}, condition <= {cond:.3g}")
                models[selection, valid is None] = model
    model = models["max", False]  # the most terms: the slowest evaluation
    _timed(f"zernike eval, {args.points} points, own column each", model, qx, qy, columns=qcols)
    _timed(f"zernike eval, {args.points} points x 10 columns", _middle_columns(model, 10), qx, qy)
    _timed("zernike residuals, all columns", model.residuals)

    def apply_like() -> None:
        """One shared design; z from 2 columns, then dx and dy from 2 columns each."""
        p = int(model.n_terms_effective.max())
        design = zernike_design(qx, qy, field_shape=SHAPE, n_terms=p)
        pair = np.column_stack([qcols, np.minimum(qcols + 1, m - 1)])
        model(qx, qy, columns=pair, design=design)
        model(qx, qy, columns=np.hstack([pair, pair[:, ::-1]]), design=design)

    _timed(f"apply-like zernike, {args.points} points (1 design, 2 + 4 columns each)", apply_like)

    nearest = FieldModel.from_estimate(
        x, y, values, kind="nearest", field_shape=SHAPE, valid=ranged
    )
    _timed(f"nearest eval, {args.points} points, own column each", nearest, qx, qy, columns=qcols)
    _timed(f"nearest leave-one-out, {n} particles x {m} columns", field_errors, nearest)

    natural = FieldModel.from_estimate(
        x, y, values, kind="natural", field_shape=SHAPE, valid=ranged
    )
    _timed(f"natural eval, {args.points} points, own column each", natural, qx, qy, columns=qcols)
    _timed(f"natural leave-one-out, {n} particles x {m} columns", field_errors, natural)
    k = args.metpy_points
    metpy_points = np.column_stack([x, y])
    _timed(
        f"MetPy natural_neighbor_to_points, {k} points, 1 column (reference)",
        natural_neighbor_to_points,
        *(metpy_points, values[:, 0], np.column_stack([qx[:k], qy[:k]])),
    )


def _middle_columns(model: FieldModel, count: int) -> FieldModel:
    """The same model restricted to ``count`` columns from the middle of the table."""
    arrays, options = model.as_arrays()
    start = model.n_columns // 2
    cols = slice(start, start + count)
    for key in ("values", "valid", "coefficients"):
        arrays[key] = arrays[key][:, cols]
    for key in ("n_terms_effective", "condition"):
        arrays[key] = arrays[key][cols]
    return FieldModel.from_arrays(arrays, options)


if __name__ == "__main__":
    main()

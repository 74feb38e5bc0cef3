"""Thread counts: numba's parallel kernels for small calls, BLAS for small linear algebra."""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager

import numba
from threadpoolctl import ThreadpoolController

#: Batches of fewer ROIs run the fit kernels (fits, sandwich errors) on one thread.
SMALL_BATCH = 128


@contextmanager
def one_thread_if(small: bool) -> Iterator[None]:
    """Run numba's parallel kernels on the calling thread alone while ``small`` is true.

    Waking the other threads costs more than a small call's work (a few ms): on a busy machine a
    kernel over four 11 x 2048 px edge bands took 9 ms on one thread and 117 ms on two.
    """
    if not small:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


@functools.cache
def _blas() -> ThreadpoolController:
    """The process's thread pools, found once (after numpy's and scipy's BLAS are loaded)."""
    return ThreadpoolController()


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run BLAS on the calling thread alone inside the block, restoring the setting after it.

    For linear algebra on matrices of a few rows, where BLAS threads only wait for each other:
    beside numba's threads on a busy 2-core machine, OpenBLAS's second thread made the
    barycentric transforms of a Delaunay triangulation of 94 points take 1-2 s instead of 0.5 ms.
    """
    with _blas().limit(limits=1, user_api="blas"):
        yield


def concurrent_kernels_safe() -> bool:
    """Whether two Python threads may launch numba's parallel kernels at once: true under the
    "omp" and "tbb" threading layers; "workqueue" aborts the process then. Asking numba for its
    thread count starts its threads, choosing the layer, if no parallel kernel has run yet."""
    numba.get_num_threads()
    return numba.threading_layer() in ("omp", "tbb")

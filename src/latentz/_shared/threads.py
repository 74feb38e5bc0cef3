"""Thread count of numba's parallel kernels for small calls."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numba

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

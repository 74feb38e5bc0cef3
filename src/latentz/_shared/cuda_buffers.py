"""Pinned host buffers and their device twins, kept per thread between calls to the GPU engine.

Pinning host memory costs far more than copying into it, so each thread keeps one pinned buffer
and one device buffer per role (for example "frames" or "fit0 rois"), or a device buffer alone
for work that never leaves the GPU, and reuses them while the shape and dtype stay the same.
Memory stays bounded: one pair per role and thread.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numba import cuda

__all__ = ["buffer_pair", "batch_size", "device_buffer"]

_local = threading.local()


def _kept(store: str, role: str, shape: int | tuple[int, ...], dtype: Any, make: Any) -> Any:
    """This thread's buffer for ``role`` in ``store``, made by ``make()`` when it has no buffer
    of ``shape`` and ``dtype`` yet."""
    cache = _local.__dict__.setdefault(store, {})
    key = (tuple(np.atleast_1d(shape)), np.dtype(dtype))
    if role not in cache or cache[role][0] != key:
        cache[role] = (key, make())
    return cache[role][1]


def buffer_pair(role: str, shape: int | tuple[int, ...], dtype: Any) -> tuple[np.ndarray, Any]:
    """(pinned host array, device array) of ``shape`` and ``dtype`` for ``role`` in this thread."""

    def make() -> tuple[np.ndarray, Any]:
        host = cuda.pinned_array(shape, dtype)
        return host, cuda.device_array_like(host)

    return _kept("pairs", role, shape, dtype, make)


def device_buffer(role: str, shape: int | tuple[int, ...], dtype: Any) -> Any:
    """A device array of ``shape`` and ``dtype`` for ``role`` in this thread (no host twin)."""
    return _kept("device", role, shape, dtype, lambda: cuda.device_array(shape, dtype))


def batch_size(n: int, capacity: int) -> int:
    """Items per batch for ``n`` items: ``n`` rounded up to a power of two (so that calls of
    similar sizes share buffers), at most ``capacity``, at least 1."""
    return max(1, min(capacity, 1 << max(n - 1, 0).bit_length()))

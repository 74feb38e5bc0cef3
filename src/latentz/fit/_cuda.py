"""CUDA twin of :func:`latentz.fit._kernels.fit_batch`: one GPU thread fits one ROI.

The per-ROI code is not written twice. The Python source of the CPU kernels (`fit_roi` and
everything it calls) is compiled a second time for numba's CUDA target, as device functions that
call each other, so both devices run the same estimators, start, damping, bounds, convergence rule
and Cramér–Rao bounds. Only the launch differs: a kernel gives each thread its work buffers in
local memory, sized for the ROI shape, and calls `fit_roi` for its ROI (the design of Gpufit).

Batches stream through the GPU: the ROIs are cut into batches of bounded size, copied from pinned
host buffers on two CUDA streams, so that one batch's copies overlap the other's fit, and the
results come back the same way. Device memory is bounded by two batches, whatever the input size.

Importing this module imports ``numba.cuda``; :mod:`latentz._shared.engine` decides whether to.
"""

from __future__ import annotations

import functools
import types
from typing import Any

import numpy as np
from numba import cuda, float64

from latentz._shared.cuda_buffers import batch_size, buffer_pair
from latentz.fit import _kernels

__all__ = ["fit_batch_cuda"]

#: The CPU device functions compiled again for CUDA, callees before callers.
_DEVICE_FUNCTIONS = (
    "log_factorial",
    "_border_mean",
    "_box_sum",
    "_start_at",
    "_start",
    "_row_start",
    "_atanh_series",
    "_log_ratio",
    "_log_likelihood",
    "_chi_square",
    "_far_deviance",
    "_evaluate",
    "_cholesky",
    "_solve",
    "_inverse_diagonal",
    "_finish",
    "_fit_one",
    "fit_roi",
)
_THREADS = 64
#: Bytes of float64 ROIs per batch; device memory holds two batches and their outputs.
_BATCH_BYTES = 64 * 2**20


@functools.cache
def _device_functions() -> dict[str, Any]:
    """CUDA device versions of `_DEVICE_FUNCTIONS`, sharing one namespace so that each calls the
    CUDA version of the others."""
    namespace = dict(vars(_kernels))
    for name in _DEVICE_FUNCTIONS:
        source = getattr(_kernels, name).py_func
        clone = types.FunctionType(
            source.__code__, namespace, source.__name__, source.__defaults__, source.__closure__
        )
        namespace[name] = cuda.jit(device=True)(clone)
    return namespace


@functools.cache
def _fit_kernel(npix: int) -> Any:
    """The fit kernel for ROIs of ``npix`` pixels (local buffers need a constant size)."""
    fit_roi = _device_functions()["fit_roi"]
    n_params = _kernels._NP

    @cuda.jit
    def fit_kernel(
        rois, start, use_start, lower_b, upper_b, method, s2, max_iter, tol,
        out_p, out_e, out_loglik, out_chi2, out_iter, out_conv,
    ):  # fmt: skip
        k = cuda.grid(1)
        if k < rois.shape[0]:
            scratch = cuda.local.array((4, npix), float64)
            vecs = cuda.local.array((7, n_params), float64)
            mats = cuda.local.array((3, n_params, n_params), float64)
            fit_roi(
                k, rois, start, use_start, lower_b, upper_b, method, s2, max_iter, tol,
                scratch, vecs, mats, out_p, out_e, out_loglik, out_chi2, out_iter, out_conv,
            )  # fmt: skip

    return fit_kernel


class _Slot:
    """Pinned host buffers, device buffers and a stream for one batch of ``size`` ROIs; slot
    ``index`` of a thread keeps its buffers between calls (:mod:`latentz._shared.cuda_buffers`)."""

    def __init__(self, index: int, size: int, roi_shape: tuple[int, int], dtype: Any) -> None:
        self.stream = cuda.stream()
        inputs = (((size, *roi_shape), dtype), ((size, 7), np.float64), (size, np.bool_))
        outputs = (
            ((size, 7), np.float64),
            ((size, 7), np.float64),
            (size, np.float64),
            (size, np.float64),
            (size, np.int64),
            (size, np.bool_),
        )
        pairs_in = [buffer_pair(f"fit{index} in{k}", *spec) for k, spec in enumerate(inputs)]
        pairs_out = [buffer_pair(f"fit{index} out{k}", *spec) for k, spec in enumerate(outputs)]
        self.host_in, self.dev_in = zip(*pairs_in, strict=True)
        self.host_out, self.dev_out = zip(*pairs_out, strict=True)
        self.pending: tuple[int, int] | None = None


def fit_batch_cuda(
    rois: np.ndarray,
    start: np.ndarray,
    use_start: np.ndarray,
    lower_b: np.ndarray,
    upper_b: np.ndarray,
    method: int,
    s2: float,
    max_iter: int,
    tol: float,
    out: tuple[np.ndarray, ...],
    *,
    batch: int | None = None,
) -> None:
    """`_kernels.fit_batch` on the GPU, with the same arguments (less ``n_chunks``); ``rois``
    may also be float32 (the arithmetic stays float64).

    ``out`` holds the six output arrays of `fit_batch` (params, errors, loglik, chi2,
    iterations, converged), written in place. ``batch`` caps the ROIs per batch (default about
    64 MiB of float64 ROIs).
    """
    n, h, w = rois.shape
    if n == 0:
        return
    batch = batch_size(n, _BATCH_BYTES // (8 * h * w) if batch is None else batch)
    kernel = _fit_kernel(h * w)
    d_lower, d_upper = cuda.to_device(lower_b), cuda.to_device(upper_b)
    slots = [_Slot(i, batch, (h, w), rois.dtype) for i in range(2 if n > batch else 1)]
    for b, first in enumerate(range(0, n, batch)):
        slot = slots[b % len(slots)]
        _collect(slot, out)
        last = min(first + batch, n)
        m = last - first
        for host, source in zip(slot.host_in, (rois, start, use_start), strict=True):
            host[:m] = source[first:last]
        for host, dev in zip(slot.host_in, slot.dev_in, strict=True):
            dev[:m].copy_to_device(host[:m], stream=slot.stream)
        d_rois, d_start, d_use = (dev[:m] for dev in slot.dev_in)
        blocks = (m + _THREADS - 1) // _THREADS
        kernel[blocks, _THREADS, slot.stream](
            d_rois, d_start, d_use, d_lower, d_upper, method, s2, max_iter, tol,
            *(dev[:m] for dev in slot.dev_out),
        )  # fmt: skip
        for host, dev in zip(slot.host_out, slot.dev_out, strict=True):
            dev[:m].copy_to_host(host[:m], stream=slot.stream)
        slot.pending = (first, last)
    for slot in slots:
        _collect(slot, out)


def _collect(slot: _Slot, out: tuple[np.ndarray, ...]) -> None:
    """Wait for the slot's batch, if any, and copy its results into ``out``."""
    if slot.pending is None:
        return
    slot.stream.synchronize()
    first, last = slot.pending
    for target, host in zip(out, slot.host_out, strict=True):
        target[first:last] = host[: last - first]
    slot.pending = None

"""numba kernel of the optics: the matrix Fourier transform of pupil fields to image intensity.

``power[k] = |ay @ field[k] @ ax|²`` for every plane ``k``. NumPy's matmul would hand these small
products to a multithreaded BLAS, which on a busy machine spends far longer waking threads than
computing; the kernel runs single-threaded, skips the zero samples outside the pupil, and writes
into an output that the caller allocated. :func:`mft_power_reference` is its plain-NumPy twin.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=True)
def mft_power(field, ay, ax, out):  # pragma: no cover - compiled; tested against the reference
    """Write ``|ay @ field[k] @ ax|²`` into ``out[k]`` (field (n, m, m), ay (ny, m), ax (m, nx),
    complex64; out (n, ny, nx) float32)."""
    n, m, _ = field.shape
    ny = ay.shape[0]
    nx = ax.shape[1]
    tmp = np.empty((m, nx), dtype=np.complex64)
    row = np.empty(nx, dtype=np.complex64)
    for k in range(n):
        for v in range(m):
            for j in range(nx):
                tmp[v, j] = 0
            for u in range(m):
                f = field[k, v, u]
                if f.real != 0 or f.imag != 0:
                    for j in range(nx):
                        tmp[v, j] += f * ax[u, j]
        for i in range(ny):
            for j in range(nx):
                row[j] = 0
            for v in range(m):
                a = ay[i, v]
                for j in range(nx):
                    row[j] += a * tmp[v, j]
            for j in range(nx):
                out[k, i, j] = row[j].real * row[j].real + row[j].imag * row[j].imag


def mft_power_reference(field: np.ndarray, ay: np.ndarray, ax: np.ndarray) -> np.ndarray:
    """Plain-NumPy twin of :func:`mft_power`, returning the float32 array."""
    amp = np.matmul(np.matmul(ay[None], field), ax[None])
    return (amp.real**2 + amp.imag**2).astype(np.float32)

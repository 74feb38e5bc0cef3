"""numba kernel for batched least-squares rotations (Kabsch by Horn's quaternion method).

For a cross-covariance ``H = Σ (a − ā)(b − b̄)ᵀ`` the rotation that minimises ``Σ |b − R a − t|²``
over proper rotations is the quaternion of the largest eigenvalue of Horn's symmetric 4 × 4 matrix
built from ``H`` (Horn, J. Opt. Soc. Am. A 4, 629 (1987)). This equals the SVD solution
``R = V diag(1, 1, det(V Uᵀ)) Uᵀ`` of Kabsch with the reflection correction, which is the NumPy
twin :func:`kabsch_rotations_numpy` the tests compare against. The kernel takes only arrays and
writes into the output allocated by the caller.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["kabsch_rotations_numba", "kabsch_rotations_numpy"]

_BLOCK = 1024
_PARALLEL_MIN = 20_000


def kabsch_rotations_numpy(h: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3) from cross-covariances ``h`` (n, 3, 3) by batched SVD (the twin)."""
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    vt = vt.copy()
    vt[..., 2, :] *= d[..., None]
    return np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)


@numba.njit(cache=True, inline="always")
def _top_eigvec4(n, e, v):
    """Cyclic Jacobi on the symmetric 4 × 4 ``n`` (overwritten, ``e`` is workspace); eigenvector of
    the largest eigenvalue into ``v``."""
    for p in range(4):
        for q in range(4):
            e[p, q] = 1.0 if p == q else 0.0
    for _sweep in range(30):
        off = 0.0
        scale = 0.0
        for p in range(4):
            for q in range(4):
                if p != q:
                    off += n[p, q] * n[p, q]
                else:
                    scale += n[p, q] * n[p, q]
        if off <= 1e-30 * scale:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = n[p, q]
                if apq == 0.0:
                    continue
                theta = (n[q, q] - n[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(4):
                    akp = n[k, p]
                    akq = n[k, q]
                    n[k, p] = c * akp - s * akq
                    n[k, q] = s * akp + c * akq
                for k in range(4):
                    apk = n[p, k]
                    aqk = n[q, k]
                    n[p, k] = c * apk - s * aqk
                    n[q, k] = s * apk + c * aqk
                n[p, q] = 0.0
                n[q, p] = 0.0
                for k in range(4):
                    ekp = e[k, p]
                    ekq = e[k, q]
                    e[k, p] = c * ekp - s * ekq
                    e[k, q] = s * ekp + c * ekq
    best = 0
    for k in range(1, 4):
        if n[k, k] > n[best, best]:
            best = k
    for k in range(4):
        v[k] = e[k, best]


@numba.njit(cache=True)
def _kabsch_block(h, start, stop, out):
    n = np.empty((4, 4))
    e = np.empty((4, 4))
    v = np.empty(4)
    for i in range(start, stop):
        _rotation_from_covariance(h, i, n, e, v, out)


@numba.njit(cache=True, parallel=True)
def _kabsch_parallel(h, out):
    n_blocks = (h.shape[0] + _BLOCK - 1) // _BLOCK
    for block in numba.prange(n_blocks):
        _kabsch_block(h, block * _BLOCK, min(h.shape[0], (block + 1) * _BLOCK), out)


def kabsch_rotations_numba(h: np.ndarray, out: np.ndarray) -> None:
    """Write into ``out`` (n, 3, 3) the rotations maximising ``tr(R h[i])`` for ``h`` (n, 3, 3).

    Threads are used only for large batches: on a busy machine a parallel launch can cost
    milliseconds, more than a small batch takes serially.
    """
    if h.shape[0] >= _PARALLEL_MIN:
        _kabsch_parallel(h, out)
    else:
        _kabsch_block(h, 0, h.shape[0], out)


@numba.njit(cache=True, inline="always")
def _rotation_from_covariance(h, i, n, e, v, out):
    """Horn's matrix of ``h[i]``, its top eigenvector, and the rotation into ``out[i]``."""
    sxx, sxy, sxz = h[i, 0, 0], h[i, 0, 1], h[i, 0, 2]
    syx, syy, syz = h[i, 1, 0], h[i, 1, 1], h[i, 1, 2]
    szx, szy, szz = h[i, 2, 0], h[i, 2, 1], h[i, 2, 2]
    n[0, 0] = sxx + syy + szz
    n[0, 1] = syz - szy
    n[0, 2] = szx - sxz
    n[0, 3] = sxy - syx
    n[1, 1] = sxx - syy - szz
    n[1, 2] = sxy + syx
    n[1, 3] = szx + sxz
    n[2, 2] = -sxx + syy - szz
    n[2, 3] = syz + szy
    n[3, 3] = -sxx - syy + szz
    for r in range(4):
        for c in range(r):
            n[r, c] = n[c, r]
    _top_eigvec4(n, e, v)
    norm = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3])
    w, x, y, z = v[0] / norm, v[1] / norm, v[2] / norm, v[3] / norm
    out[i, 0, 0] = w * w + x * x - y * y - z * z
    out[i, 0, 1] = 2.0 * (x * y - w * z)
    out[i, 0, 2] = 2.0 * (x * z + w * y)
    out[i, 1, 0] = 2.0 * (x * y + w * z)
    out[i, 1, 1] = w * w - x * x + y * y - z * z
    out[i, 1, 2] = 2.0 * (y * z - w * x)
    out[i, 2, 0] = 2.0 * (x * z - w * y)
    out[i, 2, 1] = 2.0 * (y * z + w * x)
    out[i, 2, 2] = w * w - x * x - y * y + z * z

"""Thread limits: BLAS on one thread inside ``one_blas_thread``, the caller's setting after it."""

from __future__ import annotations

from threadpoolctl import threadpool_info, threadpool_limits

from latentz._shared.threads import one_blas_thread


def _blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_one_blas_thread_limits_inside_and_restores_after():
    with threadpool_limits(2, user_api="blas"):
        before = _blas_threads()
        with one_blas_thread():
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == before


"""Where the number crunching runs: ``device="cpu" | "cuda" | "auto"``.

`resolve_device` turns the user's choice into ``"cpu"`` or ``"cuda"``. ``"cuda"`` runs detection
and the eq.-1 fits in numba's CUDA target (the optional extra ``latentz[gpu]``, which installs the
``numba-cuda`` package); ``"auto"`` picks it when a GPU is usable and otherwise falls back to the
CPU, saying so once per process. Importing latentz never imports ``numba.cuda``: this module does
so only when a device other than ``"cpu"`` is asked for.
"""

from __future__ import annotations

import functools
import os
import warnings

from latentz._shared.validate import check_choice

__all__ = ["DEVICES", "resolve_device", "cuda_status"]

#: Accepted values of every ``device`` argument.
DEVICES = ("auto", "cpu", "cuda")
_FIX = "install the GPU extra with `pip install 'latentz[gpu]'` and an NVIDIA driver"


@functools.cache
def cuda_status() -> str | None:
    """None when a CUDA GPU is usable (or numba's CUDA simulator is on), else why it is not."""
    try:
        from numba import cuda
    except ImportError as exc:  # pragma: no cover - numba always ships a cuda module stub
        return f"numba.cuda cannot be imported ({exc})"
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return None
    try:
        import numba_cuda  # noqa: F401  (the maintained CUDA target; numba's own is deprecated)
    except ImportError:
        return "the numba-cuda package is not installed"
    try:
        usable = cuda.is_available()
    except Exception as exc:  # noqa: BLE001 - a broken driver raises many kinds of error
        return f"the CUDA driver failed ({type(exc).__name__}: {exc})"
    return None if usable else "no CUDA GPU or driver was found"


@functools.cache
def _warn_cpu_fallback(reason: str) -> None:
    warnings.warn(
        f"device='auto': using the CPU because {reason}; for the GPU, {_FIX}.",
        RuntimeWarning,
        stacklevel=4,
    )


def resolve_device(device: str) -> str:
    """``"cpu"`` or ``"cuda"`` for a ``device`` argument of ``"cpu"``, ``"cuda"`` or ``"auto"``.

    Raises
    ------
    ValueError
        ``device`` is not one of `DEVICES`, or it is ``"cuda"`` and no GPU is usable.
    """
    check_choice("device", device, DEVICES)
    if device == "cpu":
        return "cpu"
    reason = cuda_status()
    if reason is None:
        return "cuda"
    if device == "cuda":
        raise ValueError(f"device='cuda' needs a usable NVIDIA GPU, but {reason}: {_FIX}.")
    _warn_cpu_fallback(reason)
    return "cpu"

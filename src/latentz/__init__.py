"""latentz: accurate 3D localization microscopy by intrinsic aberration calibration.

Implements Copeland, McGray, Ilic, Geist and Stavis, "Accurate localization microscopy by intrinsic
aberration calibration", Nat. Commun. 12, 3925 (2021). The public API, in short:

>>> import latentz as lz
>>> lz.Camera(offset=100.0, gain=0.5).gain
0.5

Names are imported on first use (PEP 562), so ``import latentz`` and the CLI start quickly.
"""

from __future__ import annotations

import importlib
from typing import Any

from latentz._version import __version__

_EXPORTS = {
    "Calibration": "latentz.calibration",
    "Camera": "latentz.camera",
    "calibrate": "latentz.calibration",
    "correct_drift": "latentz.analysis",
    "drift": "latentz.motion",
    "fit_rois": "latentz.fit",
    "frame_rate_hz": "latentz.camera",
    "frc": "latentz.analysis",
    "icp": "latentz.motion",
    "link": "latentz.motion",
    "localize": "latentz.localization",
    "motion_uncertainty": "latentz.motion",
    "read_stack": "latentz.io",
    "render": "latentz.analysis",
    "read_table": "latentz.io",
    "render_rois": "latentz.fit",
    "rigid_motion": "latentz.motion",
    "table1": "latentz.motion",
    "write_table": "latentz.io",
}

__all__ = [
    "__version__",
    "Calibration",
    "Camera",
    "calibrate",
    "correct_drift",
    "drift",
    "fit_rois",
    "frame_rate_hz",
    "frc",
    "icp",
    "link",
    "localize",
    "motion_uncertainty",
    "read_stack",
    "render",
    "read_table",
    "render_rois",
    "rigid_motion",
    "table1",
    "write_table",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'latentz' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))

"""latentz: accurate 3D localization microscopy by intrinsic aberration calibration.

Implements Copeland, McGray, Ilic, Geist and Stavis, "Accurate localization microscopy by intrinsic
aberration calibration", Nat. Commun. 12, 3925 (2021).
"""

from latentz._version import __version__
from latentz.camera import Camera
from latentz.io import read_stack, read_table, write_table

__all__ = [
    "__version__",
    "Camera",
    "read_stack",
    "read_table",
    "write_table",
]

"""The camera: its model (offset, gain, read noise, flatfield), its readout timing, and where a
run's camera values come from."""

from latentz.camera.model import Camera
from latentz.camera.readout import frame_rate_hz

__all__ = ["Camera", "frame_rate_hz"]

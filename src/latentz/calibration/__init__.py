"""Through-focus calibration of the microscope's intrinsic aberrations (paper Figs. 2–3).

Local calibration of each calibration particle (traces, z_f, Δx'(z), Δy'(z), z(shape), σ's),
culling, tilt removal, 3D localization with the nearest particle's models, and the figures; the
field models and the aperture-array magnification live beside them.
"""

from latentz.calibration.apertures import ApertureLattice
from latentz.calibration.fieldmodels import FieldModel, field_errors
from latentz.calibration.figures import figure2, figure3, figure_focus, figure_shape_zero
from latentz.calibration.local import LocalOptions
from latentz.calibration.polymodel import PolyModel
from latentz.calibration.result import FIELD_MODELS, Calibration
from latentz.calibration.shape import SHAPES, astigmatism_angle, shape_value
from latentz.calibration.tilt import TiltPlane
from latentz.calibration.traces import Traces, extract_traces, find_particles
from latentz.calibration.workflow import calibrate, calibrate_traces

__all__ = [
    "FIELD_MODELS",
    "SHAPES",
    "ApertureLattice",
    "Calibration",
    "FieldModel",
    "LocalOptions",
    "PolyModel",
    "TiltPlane",
    "Traces",
    "astigmatism_angle",
    "calibrate",
    "calibrate_traces",
    "extract_traces",
    "field_errors",
    "figure2",
    "figure3",
    "figure_focus",
    "figure_shape_zero",
    "find_particles",
    "shape_value",
]

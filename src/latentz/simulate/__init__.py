"""A simulated widefield microscope with intrinsic, field-dependent aberrations.

Scalar pupil-function optics (:class:`Optics`), Zernike aberrations that vary across the field
(:class:`AberrationMap`), point emitters and fluorescent particles, pixel integration, and a camera
with shot noise, read noise, offset, gain and 16-bit saturation. Datasets come with ground truth:
through-focus calibration stacks, test spots, aperture arrays and the paper's rotating microgear.
"""

from latentz.simulate.aberrations import MODE_NAMES, AberrationMap
from latentz.simulate.datasets import (
    ApertureArrayDataset,
    CalibrationDataset,
    aperture_array,
    calibration_dataset,
    render_spots,
    stage_origins,
)
from latentz.simulate.figures import psf_gallery, save_psf_gallery
from latentz.simulate.files import write_files
from latentz.simulate.gear import GearMovie, gear_movie
from latentz.simulate.optics import Optics
from latentz.simulate.presets import DATASET_KINDS, write_dataset

__all__ = [
    "AberrationMap",
    "ApertureArrayDataset",
    "CalibrationDataset",
    "DATASET_KINDS",
    "GearMovie",
    "MODE_NAMES",
    "Optics",
    "aperture_array",
    "calibration_dataset",
    "gear_movie",
    "psf_gallery",
    "render_spots",
    "save_psf_gallery",
    "stage_origins",
    "write_dataset",
    "write_files",
]

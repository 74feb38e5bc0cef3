"""A napari reader (``pip install 'latentz[napari]'``): localization files open as 3D points
coloured by z with their errors as features; calibration files as the particles and maps of
best focus and sigma_z across the field. Its manifest is ``napari.yaml`` beside this file."""

from latentz.viewer.reader import get_reader, layers_of_calibration, layers_of_localizations

__all__ = ["get_reader", "layers_of_calibration", "layers_of_localizations"]

"""Localizing emitters in movies: the full mode (:mod:`~latentz.localization.movie`), the
follow mode of ``localize(track=True)`` (:mod:`~latentz.localization.follow`), and the per-spot
quality verdict (:mod:`~latentz.localization.quality`)."""

from latentz.localization.movie import (
    LOCALIZE_COLUMNS,
    check_camera_offset,
    check_roi_fits,
    localize,
)

__all__ = ["LOCALIZE_COLUMNS", "check_camera_offset", "check_roi_fits", "localize"]

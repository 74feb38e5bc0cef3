"""Physical sanity checks that warn (never raise): each warning names the value and the range
expected, so a plausible-looking but wrong setting does not pass silently."""

import warnings

import numpy as np


class LatentzWarning(UserWarning):
    """A physically implausible input that latentz accepted but the user should look at."""


def warn(message: str) -> None:
    """Issue one :class:`LatentzWarning` line (for checks that live beside their data)."""
    warnings.warn(message, LatentzWarning, stacklevel=3)


def check_offset(offset_adu: float, frame_median_adu: float) -> None:
    """Warn if the camera offset (ADU) is above the image median (ADU)."""
    if offset_adu > frame_median_adu:
        warn(
            f"Camera offset {offset_adu:g} ADU is above the image median "
            f"{frame_median_adu:g} ADU; expected offset <= {frame_median_adu:g} ADU."
        )


def check_pixel_size(pixel_nm: float, calibration_pixel_nm: float, *, rtol: float = 0.01) -> None:
    """Warn if a pixel size (nm) differs from the calibration's by more than ``rtol``."""
    low, high = calibration_pixel_nm * (1 - rtol), calibration_pixel_nm * (1 + rtol)
    if not low <= pixel_nm <= high:
        warn(
            f"Pixel size {pixel_nm:g} nm is inconsistent with the calibration's "
            f"{calibration_pixel_nm:g} nm; expected {low:g}..{high:g} nm."
        )


def check_roi_size(roi_size: int | None, calibration_roi_size: int) -> None:
    """Warn if spots were fitted in a ROI (pixels) other than the calibration's: the fitted
    widths, and so the shape value and z, depend on the ROI. None (unknown) passes."""
    if roi_size is not None and int(roi_size) != int(calibration_roi_size):
        warn(
            f"The spots were fitted in a {roi_size} px ROI but the calibration in "
            f"{calibration_roi_size} px; z is biased. Use lz.localize(frames, calibration=cal), "
            f"or roi_size={calibration_roi_size}."
        )


#: Plausible growth of a defocused spot's Gaussian width per unit of defocus: about
#: tan(asin(NA / n)) / 2 far from focus, less near it; 0.02..3 spans air and oil objectives.
DEFOCUS_RATE = (0.02, 3.0)


def check_z_step(z_step_nm: float, width_rate: float) -> None:
    """Warn if the spot widths change implausibly fast or slowly per nm of the given z.

    ``width_rate`` is the measured change of the fitted width (nm) per nm of z when the planes
    are ``z_step_nm`` apart; a z step off by a factor of ten, or in µm for nm, takes it outside
    :data:`DEFOCUS_RATE`. The warning names the z step that the widths imply.
    """
    low, high = DEFOCUS_RATE
    if np.isfinite(width_rate) and not low <= width_rate <= high:
        step_low, step_high = z_step_nm * width_rate / high, z_step_nm * width_rate / low
        warn(
            f"z step {z_step_nm:g} nm makes the spot widths change by {width_rate:.3g} nm per nm "
            f"of z; expected {low:g}..{high:g} for defocus, that is a z step of "
            f"{step_low:.3g}..{step_high:.3g} nm."
        )


def check_widths(
    widths: np.ndarray, calibrated: tuple[float, float], *, factor: float = 2.0
) -> None:
    """Warn if any spot width (pixels) is more than ``factor`` outside the calibrated range."""
    widths = np.asarray(widths, dtype=float)
    widths = widths[np.isfinite(widths)]
    low, high = calibrated[0] / factor, calibrated[1] * factor
    outside = (widths < low) | (widths > high)
    if outside.any():
        warn(
            f"{int(outside.sum())} spot widths (e.g. {widths[outside][0]:g} px) are far "
            f"outside the calibrated {calibrated[0]:g}..{calibrated[1]:g} px; "
            f"expected {low:g}..{high:g} px."
        )

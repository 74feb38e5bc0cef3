"""Physical sanity checks that warn (never raise): each warning names the value and the range
expected, so a plausible-looking but wrong setting does not pass silently."""

import warnings

import numpy as np


class LatentzWarning(UserWarning):
    """A physically implausible input that latentz accepted but the user should look at."""


def _warn(message: str) -> None:
    warnings.warn(message, LatentzWarning, stacklevel=3)


def check_offset(offset_adu: float, frame_median_adu: float) -> None:
    """Warn if the camera offset (ADU) is above the image median (ADU)."""
    if offset_adu > frame_median_adu:
        _warn(
            f"Camera offset {offset_adu:g} ADU is above the image median "
            f"{frame_median_adu:g} ADU; expected offset <= {frame_median_adu:g} ADU."
        )


def check_pixel_size(pixel_nm: float, calibration_pixel_nm: float, *, rtol: float = 0.01) -> None:
    """Warn if a pixel size (nm) differs from the calibration's by more than ``rtol``."""
    low, high = calibration_pixel_nm * (1 - rtol), calibration_pixel_nm * (1 + rtol)
    if not low <= pixel_nm <= high:
        _warn(
            f"Pixel size {pixel_nm:g} nm is inconsistent with the calibration's "
            f"{calibration_pixel_nm:g} nm; expected {low:g}..{high:g} nm."
        )


def check_z_step(z_step_nm: float, n_slices: int, z_range_nm: tuple[float, float]) -> None:
    """Warn if ``n_slices`` steps of ``z_step_nm`` do not span about the expected z range (nm)."""
    span = abs(z_step_nm) * (n_slices - 1)
    low, high = z_range_nm
    expected = high - low
    if expected > 0 and not 0.5 * expected <= span <= 2.0 * expected:
        _warn(
            f"z step {z_step_nm:g} nm over {n_slices} slices spans {span:g} nm; expected a span "
            f"of {0.5 * expected:g}..{2.0 * expected:g} nm (the range {low:g}..{high:g} nm)."
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
        _warn(
            f"{int(outside.sum())} spot widths (e.g. {widths[outside][0]:g} px) are far "
            f"outside the calibrated {calibrated[0]:g}..{calibrated[1]:g} px; "
            f"expected {low:g}..{high:g} px."
        )

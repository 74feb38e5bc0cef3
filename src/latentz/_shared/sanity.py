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


#: Plausible depth of focus d over squared in-focus width σ0² of a spot's Gaussian width, nm⁻¹
#: (:mod:`latentz.calibration.depth`). A paraxial Gaussian beam has d / σ0² = 4π n / λ: from
#: 0.0168 (air, λ 750 nm) to 0.042 (n 1.52, λ 450 nm). Measured spots lie up to 2x below it:
#: 0.009 on the SMLM 2016 beads (NA 1.49-like, astigmatic), 0.013-0.018 on the fit3Dcspline bead,
#: 0.012 and 0.017 on latentz's simulator (NA 0.55 in air, 1 µm and 100 nm particles). The
#: window allows 5x below and 1.5x above the paraxial range, so a z step 10x off either way
#: leaves it on every one of those.
DEPTH_RATIO_PER_NM = (4 * np.pi / 750.0 / 5, 4 * np.pi * 1.52 / 450.0 * 1.5)


def check_z_step(z_step_nm: float, depth_ratio_per_nm: float) -> None:
    """Warn if the spot widths' depth of focus contradicts the given z step.

    ``depth_ratio_per_nm`` is d / σ0² measured with planes ``z_step_nm`` apart; d scales with
    the z step, so a step off by k moves it by k, outside :data:`DEPTH_RATIO_PER_NM` for k = 10
    or 1/10 (or µm given for nm). The warning names the z step that the widths imply.
    """
    low, high = DEPTH_RATIO_PER_NM
    ratio = depth_ratio_per_nm
    if np.isfinite(ratio) and ratio > 0 and not low <= ratio <= high:
        step_low, step_high = z_step_nm * low / ratio, z_step_nm * high / ratio
        warn(
            f"z step {z_step_nm:g} nm makes the spot widths' depth of focus d = {ratio:.3g} σ0² "
            f"per nm (σ0 the in-focus width); expected {low:.3g}..{high:.3g} from the optics "
            f"(4π n / λ), that is a z step of {step_low:.3g}..{step_high:.3g} nm."
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

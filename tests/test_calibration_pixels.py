"""localize's refit on the calibration's pixel (:func:`latentz.localization.recentre.
on_calibration_pixels`): a spot that the calibration moves by more than half a pixel is fitted
again in the ROI centred on its corrected place; the rest keep their fits."""

from types import SimpleNamespace

import numpy as np
import pandas as pd

from latentz.detect import cut_photons, roi_windows
from latentz.localization.recentre import SHIFT_PX, fit_recentred, on_calibration_pixels

ROI = 11
PIXEL_NM = 100.0


def _frame(places: np.ndarray, sigma_px: float = 1.3, photons: float = 5e3) -> np.ndarray:
    """One noise-free frame (photoelectrons) of round Gaussian spots at ``places`` (x, y px)
    on a background of 10."""
    yy, xx = np.mgrid[:64, :96].astype(float)
    frame = np.full(xx.shape, 10.0)
    for x, y in places:
        frame += (
            photons
            / (2 * np.pi * sigma_px**2)
            * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma_px**2))
        )
    return frame[None]


class _ShiftingCalibration:
    """Stands in for a calibration whose lateral correction is ``shift`` (px, per spot in
    order): ``apply`` puts each spot's corrected place at its fitted centre less its shift
    (with or without errors: it has none)."""

    def __init__(self, shift: np.ndarray) -> None:
        self.shift = shift
        self.camera = SimpleNamespace(pixel_size_nm=PIXEL_NM)

    def apply(self, table: pd.DataFrame, *, errors: bool = True) -> pd.DataFrame:
        return table.assign(x_nm=(table["x"] - self.shift[:, 0]) * PIXEL_NM,
                            y_nm=(table["y"] - self.shift[:, 1]) * PIXEL_NM,
                            in_range=True)  # fmt: skip


def test_only_spots_moved_beyond_half_a_pixel_are_fitted_again_on_their_place():
    places = np.array([[20.3, 20.6], [50.2, 30.4], [75.7, 40.1], [90.4, 32.0]])
    block = _frame(places)
    centres = np.rint(places[:, ::-1]).astype(np.int64)  # (row, col)
    row0, col0, windows, _ = roi_windows(centres[:, 0], centres[:, 1], ROI, block.shape[1:])
    frames = np.zeros(len(places), np.int64)

    def read(moved, r0, c0):
        return cut_photons(block, frames[moved], r0, c0, ROI)

    rois = read(np.ones(len(places), bool), row0, col0)
    done = fit_recentred(read, rois, (row0, col0), (centres[:, 0], centres[:, 1]),
                         frame_shape=block.shape[1:], method="mle", readnoise=0.0,
                         windows=windows, device="cpu")  # fmt: skip
    # spot 0 within half a pixel; 1 and 2 beyond it; 3's new ROI would leave the frame
    shift = np.array([[0.4, -0.3], [2.0, 0.0], [-0.2, -1.6], [-4.0, 0.0]])
    assert np.all((np.abs(shift).max(axis=1) > SHIFT_PX) == [False, True, True, True])
    after = on_calibration_pixels(done, read, _ShiftingCalibration(shift),
                                  frame_shape=block.shape[1:], method="mle", readnoise=0.0,
                                  device="cpu")  # fmt: skip
    place = np.rint(done.fit.params[:, :2] - shift).astype(np.int64)  # (col, row)
    half = ROI // 2
    moved = np.array([False, True, True, False])
    np.testing.assert_array_equal(after.col0[moved], place[moved, 0] - half)
    np.testing.assert_array_equal(after.row0[moved], place[moved, 1] - half)
    for kept in np.flatnonzero(~moved):
        assert after.col0[kept] == done.col0[kept] and after.row0[kept] == done.row0[kept]
        np.testing.assert_array_equal(after.fit.params[kept], done.fit.params[kept])
    # the moved spots, off-centre in their new ROIs, are still found where they are
    np.testing.assert_allclose(after.fit.params[moved, :2], places[moved], atol=0.02)
    assert np.all(np.isfinite(after.fit.errors[moved]))
    np.testing.assert_array_equal(after.rois[moved], read(moved, after.row0[moved],
                                                          after.col0[moved]))  # fmt: skip

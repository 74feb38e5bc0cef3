"""Single emitters far below focus stay single and are located: the SMLM 2016 AS bead stack's
beads 0-2 calibrate (defaults); emitters drawn from the held-out beads 3-5 (their averaged
images, :class:`latentz.simulate.bead_psf.BeadPSF`), bright (8,000 photons) and far apart (one
per 32 px cell), 380-600 nm below the stack's focus, where the image is long along one axis
and not Gaussian. EMCCD frames as in benchmarks/bench_challenge.py. Truth is where each
emitter was drawn: one emitter per cell."""

import warnings

import numpy as np
import pandas as pd
import pytest
from realdata import SMLM_CAMERA, need, smlm_beads
from scipy.spatial import cKDTree

import latentz as lz
from latentz.simulate.bead_psf import BeadPSF
from latentz.simulate.emccd import expose_emccd

pytestmark = pytest.mark.realdata

CELL, CELLS, N_FRAMES = 32, 4, 6
PHOTONS, BACKGROUND = 8000.0, 10.0


def _frames(
    psf: BeadPSF, seed: int, *depths: tuple[float, float]
) -> tuple[np.ndarray, pd.DataFrame]:
    """EMCCD frames (ADU: EM gain 100, 10 e-/ADU, 50 e- read noise, offset 100) with one emitter
    near the middle of every cell, cell k at a uniform z in ``depths[k % len(depths)]`` (nm, the
    stack's z), and their truth (frame, x, y px, z_nm, depth: that index)."""
    rng = np.random.default_rng(seed)
    n = N_FRAMES * CELLS**2
    cell = np.tile(np.indices((CELLS, CELLS)).reshape(2, -1).T, (N_FRAMES, 1))
    truth = pd.DataFrame({"frame": np.repeat(np.arange(N_FRAMES), CELLS**2),
                          "x": (cell[:, 1] + 0.5) * CELL + rng.uniform(-2, 2, n),
                          "y": (cell[:, 0] + 0.5) * CELL + rng.uniform(-2, 2, n),
                          "depth": np.arange(n) % len(depths)})  # fmt: skip
    lo, hi = np.array(depths)[truth["depth"]].T
    truth["z_nm"], truth["photons"] = rng.uniform(lo, hi), PHOTONS
    side = CELL * CELLS
    expected = psf.render(truth, n_frames=N_FRAMES, frame_shape=(side, side),
                          background=BACKGROUND)  # fmt: skip
    frames = expose_emccd(expected, rng, em_gain=100.0, e_per_adu=10.0, readnoise_e=50.0,
                          offset_adu=100.0)  # fmt: skip
    return frames, truth


@pytest.fixture(scope="module")
def calibration_and_psf():
    """The defaults' calibration of beads 0-2 and the PSF of the held-out beads 3-5."""
    stack, z = smlm_beads()
    beads = pd.read_csv(need("smlm2016-as-beads.csv"))
    at = beads[beads["plane"] == 0].set_index("bead")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = lz.calibrate(stack[:, :95, :110], z, camera=lz.Camera(**SMLM_CAMERA))
    photons = (stack - SMLM_CAMERA["offset"]) * SMLM_CAMERA["gain"]
    centres = at.loc[[3, 4, 5], ["x_nm", "y_nm"]].to_numpy() / 100 - 0.5  # pixel centres
    return cal, BeadPSF.from_stack(photons, z, centres)


def _localize(cal, frames: np.ndarray) -> pd.DataFrame:
    camera = lz.Camera(offset=100.0, gain=0.1, readnoise=0.5, pixel_size_nm=100.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lz.localize(frames, calibration=cal, camera=camera)


def test_far_from_focus_a_single_emitter_is_one_row(calibration_and_psf):
    """Each cell holds one emitter, so a cell with more than one row holds a false one: the
    two-emitter fit splitting one long, non-Gaussian spot into two (it did so for 29 of these
    96 emitters while a split was kept whenever each half looked like some emitter). Fewer than
    1 in 10 may be split."""
    cal, psf = calibration_and_psf
    frames, truth = _frames(psf, 1, (-540.0, -380.0))
    table = _localize(cal, frames)
    rows = table[table["converged"] & ~table["duplicate"]]
    cell = (rows["frame"].to_numpy() * CELLS + rows["y"].to_numpy() // CELL) * CELLS + (
        rows["x"].to_numpy() // CELL)
    per_cell = np.bincount(cell.astype(int), minlength=len(truth))
    assert np.all(per_cell >= 1)
    assert np.sum(per_cell > 1) < 0.1 * len(truth)


def test_the_calibrated_range_reaches_as_far_as_the_beads_fit(calibration_and_psf):
    """Emitters 540-600 nm below the stack's focus (the last 60 nm of the challenge-like
    frames' range; the beads' images reach 750 nm), in every other cell, are located: at least
    80 % of them are good rows at their place. When the beads' fits there were cut at 50
    iterations and dropped, the curves ended 560-580 nm below focus and 9 of these 48 were.
    Their z is not held here: after one offset (the median error of the emitters within 200 nm
    of focus in the other cells; latentz's z = 0 is the beads' focus, not the stack's) their
    median error is 37 nm toward focus."""
    cal, psf = calibration_and_psf
    frames, truth = _frames(psf, 2, (-200.0, 200.0), (-600.0, -540.0))
    table = _localize(cal, frames)
    good = table[table["good"]]
    at = cKDTree(truth[["x", "y"]].to_numpy() + truth[["frame"]].to_numpy() * [1000, 0])
    d, i = at.query(good[["x", "y"]].to_numpy() + good[["frame"]].to_numpy() * [1000, 0])
    far = np.unique(i[(d < 2.0) & (truth["depth"].to_numpy()[i] == 1)])
    assert far.size >= 0.8 * (truth["depth"] == 1).sum()

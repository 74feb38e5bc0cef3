"""The quality verdicts against truth, on simulated single molecules of random astigmatic
microscopes, each calibrated with defaults on its own simulated 100 nm beads
(:mod:`latentz.validation.molecules`). Truth is where the simulation put each molecule; a
localization is correct when the challenge's matching pairs it with one (250 nm laterally,
500 nm axially, one z offset removed)."""

import warnings

import numpy as np
import pytest

from latentz._shared.sanity import LatentzWarning
from latentz.localization.mismatch import check_calibration_fits
from latentz.localization.quality import FLAGS
from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import (
    bead_calibration,
    localized_molecules,
    true_positives,
    wrong_microscopes,
)

pytestmark = pytest.mark.slow


def _flagged(locs, flag):
    return (
        ~locs["converged"].to_numpy(bool) if flag == "not_converged" else locs[flag].to_numpy(bool)
    )


@pytest.fixture(scope="module")
def molecule_sets():
    """Two random microscopes (astigmatism 50–90 nm RMS), molecules of 300–10,000 photons
    within ±600 nm at 0.5 and 1.5 per µm²."""
    sets = []
    for seed in (21, 22):
        rng = np.random.default_rng(seed)
        microscope = random_microscope(rng)
        cal = bead_calibration(microscope, seed)
        for density in (0.5, 1.5):
            sets.append(localized_molecules(microscope, cal, rng, density_per_um2=density,
                                            n_frames=4))  # fmt: skip
    return sets


def test_each_flag_alone_loses_at_most_2_percent_of_the_correct_localizations(molecule_sets):
    everything = true_positives(molecule_sets)
    # binomial sampling error of a 2 % share over these localizations (~1,500 correct)
    allowance = 0.02 + 2 * np.sqrt(0.02 * 0.98 / everything)
    for flag in FLAGS:
        kept = true_positives(molecule_sets, lambda locs, f=flag: ~_flagged(locs, f))
        assert 1 - kept / everything <= allowance, (flag, 1 - kept / everything)


def test_good_keeps_90_percent_of_the_correct_localizations_and_drops_most_wrong_ones(
    molecule_sets,
):
    everything = true_positives(molecule_sets)
    good = true_positives(molecule_sets, lambda locs: locs["good"].to_numpy(bool))
    spread = 2 * np.sqrt(0.1 * 0.9 / everything)  # binomial sampling error of a 90 % share
    assert good / everything >= 0.90 - spread, good / everything
    wrong = np.concatenate([~locs["correct"].to_numpy(bool) for locs, *_ in molecule_sets])
    kept = np.concatenate([locs["good"].to_numpy(bool) for locs, *_ in molecule_sets])
    assert kept[wrong].mean() <= 0.5  # the flags earn their keep: most wrong rows go


@pytest.mark.parametrize("seed", [31, 32, 33])
def test_a_right_calibration_of_a_weakly_astigmatic_microscope_is_never_condemned(seed):
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, astigmatism_nm=(20.0, 30.0))  # weak astigmatism
    cal = bead_calibration(microscope, seed)
    locs, _, _ = localized_molecules(
        microscope, cal, rng, density_per_um2=0.5, n_frames=4,
        photons=(1e3, 1e4), z_range_nm=(-400.0, 400.0),
    )  # fmt: skip
    with warnings.catch_warnings():  # the table-level test localize ran, run again in the open
        warnings.filterwarnings("error", message="The calibration does not fit")
        check_calibration_fits(locs, cal)
    assert not locs["inconsistent"].all()
    located = locs["correct"] & locs["in_range"]
    share = locs["good"][located].mean()
    # ~250 correct in-range rows per microscope: 2 binomial SE of a 90 % share is ~4 %
    assert share >= 0.90 - 2 * np.sqrt(0.1 * 0.9 / located.sum()), share


@pytest.mark.parametrize(
    "wrong, cause",
    [("axis 45° off", "other axes"), ("pixel size 1.25x", "widths are 1"),
     ("wavelength 1.2x", "fall short of the calibration's by a blur")],
)  # fmt: skip
def test_a_calibration_of_another_microscope_is_caught(wrong, cause):
    """Beads of a microscope that differs in one thing calibrate it; its molecules (10³–10⁴
    photons) are localized with that calibration. Not among them: the axis turned by 90°, which
    mirrors z and fits the shapes as well as the right calibration. The wavelength 1.2x puts
    the log width ratio of this strongly astigmatic microscope's molecules within the right
    calibrations' range (−0.05), but their widths fall short of the calibration's by a blur of
    about 60 nm, where 100 nm beads give at most 37 nm. The issue's table: molecules within
    ±400 nm, 6 frames (~280 spots); 4 frames within ±600 nm (168 spots) measure that blur as
    52 ± 23 nm, not beyond 50 nm by a standard error."""
    rng = np.random.default_rng(41)
    microscope = random_microscope(rng)
    calibration = bead_calibration(wrong_microscopes(microscope)[wrong], 41)
    locs, _, _ = localized_molecules(
        microscope, calibration, rng, density_per_um2=0.5, n_frames=6, photons=(1e3, 1e4),
        z_range_nm=(-400.0, 400.0),
    )  # fmt: skip
    assert not locs["good"].any()
    with pytest.warns(LatentzWarning, match=cause):  # what localize said, said again
        check_calibration_fits(locs, calibration)


def test_at_an_11_px_roi_out_of_range_loses_at_most_2_percent_of_the_correct_localizations():
    """The microscope of seed 2 calibrated at an 11 px ROI: defocused images fill it and the
    shape flattens towards the ends of the calibrated range, where a held-out particle's dimmed
    image, read through its partner's flat inverse, errs by up to 10⁷ nm. Those planes do not
    count towards the dimming transfer's σ (as they do not in the pair table), so no spot's z
    error is wider than the span the calibration imaged."""
    from latentz.calibration.dim_crossval import transfer_sigma

    rng = np.random.default_rng(2)
    microscope = random_microscope(rng)
    cal = bead_calibration(microscope, 2, roi_size=11)
    span = float(np.nanmax(cal.z_span_nm[:, 1] - cal.z_span_nm[:, 0]))
    assert np.all(transfer_sigma(cal)[2] <= span)
    sets = [localized_molecules(microscope, cal, rng, density_per_um2=d, n_frames=6)
            for d in (0.5, 1.0, 2.0)]  # fmt: skip
    everything = true_positives(sets)
    kept = true_positives(sets, lambda locs: ~locs["out_of_range"].to_numpy(bool))
    # 2 % plus 2 binomial standard errors over ~750 correct localizations (~1 %)
    assert 1 - kept / everything <= 0.02 + 2 * np.sqrt(0.02 * 0.98 / everything), kept / everything

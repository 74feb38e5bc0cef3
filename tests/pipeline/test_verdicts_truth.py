"""The quality verdicts against truth, on simulated single molecules of random astigmatic
microscopes, each calibrated with defaults on its own simulated 100 nm beads
(:mod:`latentz.validation.molecules`). Truth is where the simulation put each molecule; a
localization is correct when the challenge's matching pairs it with one (250 nm laterally,
500 nm axially, one z offset removed)."""

import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from latentz._shared.sanity import LatentzWarning
from latentz.localization.mismatch import check_calibration_fits
from latentz.localization.quality import FLAGS
from latentz.simulate.molecules import random_microscope
from latentz.validation.challenge import offset_pairs
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
    # each measurement counted once: at 1.5 per µm² several detections of one spot, where
    # molecules lie within a pixel of each other, converge on one fit, and the challenge's
    # tolerances would match each copy to one of those molecules; the duplicate flag keeps one
    everything = true_positives(molecule_sets)
    # binomial sampling error of a 2 % share over these localizations (~900 correct)
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
    [("axis 45° off", "widths are 1"), ("pixel size 1.25x", "widths are 1"),
     ("wavelength 1.2x", "fall short of the calibration's by a blur")],
)  # fmt: skip
def test_a_calibration_of_another_microscope_is_caught(wrong, cause):
    """Beads of a microscope that differs in one thing calibrate it; its molecules (10³–10⁴
    photons) are localized with that calibration. Not among them: the axis turned by 90°, which
    mirrors z and fits the shapes as well as the right calibration. The axis turned by 45°: z is
    read near focus, where that calibration's shapes come nearest the spots', and the spots are
    wider than the calibration's at that z (+0.19 ± 0.02 in log width ratio); its curves turned
    back fit the spots best as well. The wavelength 1.2x puts
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


def _crowded(truth, half_px=7.0):
    """Whether another molecule of the same frame lies within ``half_px`` in x and in y."""
    points = truth[["x", "y", "frame"]].to_numpy(float) * [1.0, 1.0, 1e4]
    tree = cKDTree(points)
    return tree.query_ball_point(points, half_px, p=np.inf, return_length=True) > 1


def _good_errors(molecule_sets):
    """Errors (nm, against where the simulation put each molecule), reported 1σ and whether
    the row is one of a two-emitter fit, of the correct good rows whose molecule has another
    molecule within 7 px (inside its 15 px ROI), or that are a pair's."""
    parts = []
    for locs, truth, _ in molecule_sets:
        pairs, _ = offset_pairs(truth, locs)
        rows = locs.loc[pairs["locs_row"]]
        crowded = _crowded(truth)[truth.index.get_indexer(pairs["truth_row"])]
        paired = (rows["pair"] >= 0).to_numpy()
        keep = rows["good"].to_numpy(bool) & (crowded | paired)
        part = pd.DataFrame({"paired": paired[keep]})
        for a in "xyz":
            part[f"d{a}"] = pairs[f"d{a}_nm"].to_numpy()[keep]
            part[f"s{a}"] = rows[f"{a}_err_nm"].to_numpy()[keep]
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


@pytest.mark.parametrize("kind", ["single", "pair"])
def test_crowded_and_pair_rows_errors_lie_within_their_1_sigma_as_measured(molecule_sets, kind):
    """Good rows with another molecule inside the ROI (one-emitter fits) and good rows of
    two-emitter fits: the share of x, y and z errors within the reported 1σ lies within
    0.50–0.88. On six microscopes at 0.2–2 per µm² (benchmarks/bench_crowding.py) all good
    one-emitter rows cover 49–74 % and pair rows 74–83 %; the band adds 2 binomial standard
    errors at this test's ~330 crowded one-emitter and ~120 pair rows (5 and 8 %). The fit's
    own errors alone cover 16–63 % (one emitter) and 27–59 % (pairs) there, and fail it."""
    rows = _good_errors(molecule_sets)
    rows = rows[rows["paired"] == (kind == "pair")]
    covered = {a: np.mean(np.abs(rows[f"d{a}"]) <= rows[f"s{a}"]) for a in "xyz"}
    assert len(rows) >= 100 and all(0.50 <= c <= 0.88 for c in covered.values()), (
        len(rows),
        covered,
    )

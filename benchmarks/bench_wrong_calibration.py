"""The wrong-calibration test against truth: its statistic on right and on wrong calibrations.

For one random astigmatic microscope with strong (50-90 nm RMS), one with weak (20-30 nm RMS)
and one with very weak (3-8 nm RMS: widths within 0.93-1.08 of each other over ±400 nm)
astigmatism (:func:`latentz.simulate.molecules.random_microscope`), molecules of 1,000-10,000
photons within ±400 nm at 0.5 per µm² are localized with calibrations made, with defaults, on
simulated 100 nm beads (:func:`latentz.validation.molecules.bead_calibration`) of: the same
microscope (right), and microscopes that differ in one thing: the astigmatism's axis turned by
90° or 45°, the pixel size 1.25x, the wavelength 1.2x. ``--right`` more microscopes of each
kind (seeds from ``--start``) get their right calibration (false alarms), one whose axis lies
90° and one 45° off and one at 1.2x the wavelength. For each: the median ``consistency_chi2``
of the converged, unique spots, the measurements of
:func:`latentz.localization.mismatch.calibration_mismatch` (axis in degrees, the χ² that turn
gains, log width ratio and blur in nm, each ± its standard error), whether
:func:`latentz.localization.mismatch.check_calibration_fits` warns, the share of the correct,
in-range localizations that are good, and the harm: the z RMSE (± its standard error) and
lateral RMSE of the converged, unique, in-range spots against the truth (each paired with the
nearest molecule within 250 nm laterally at any depth, one z offset removed:
:func:`latentz.validation.challenge.offset_pairs`), and the z RMSE over the right
calibration's on the same frames, which says whether a wrong calibration that is not caught
costs z. For right calibrations, how often small tables blame the axis: the share of
:data:`SUBSETS` random draws of 20, 40 and 80 of the checked spots whose axis is off. Writes
``results/bench_wrong_calibration.md`` (``_start<n>`` before ``.md`` from another ``--start``).

Run: ``python benchmarks/bench_wrong_calibration.py [--right 3] [--start 1]
[--kinds strong weak "very weak"]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_verdicts import markdown

from latentz.calibration import Calibration
from latentz.localization import mismatch
from latentz.simulate.molecules import random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.molecules import with_calibration_of, wrong_microscopes

MICROSCOPES = {"strong": (11, (50.0, 90.0)), "weak": (12, (20.0, 30.0)),
               "very weak": (13, (3.0, 8.0))}  # fmt: skip


#: Random draws of each small table size (spots) of a right calibration's checked spots.
SUBSETS = 100
SMALL_TABLES = (20, 40, 80)

#: The calibrations that the ``--right`` microscopes get.
EXTRA = ("right", "axis 90° off", "axis 45° off", "wavelength 1.2x")


def scores(kind: str, seed: int, astigmatism: tuple[float, float], only_right: bool) -> list:
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, astigmatism_nm=astigmatism)
    out, right = [], {}
    for name in wrong_microscopes(microscope):
        if only_right and name not in EXTRA:
            continue
        locs, truth, cal = with_calibration_of(microscope, name, seed)
        checked = (
            locs["converged"] & ~locs["duplicate"] & np.isfinite(locs["consistency_chi2"])
        ).to_numpy(bool)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mismatch.check_calibration_fits(locs, cal)
        found = mismatch.calibration_mismatch(locs, cal)
        located = (locs["correct"] & locs["in_range"]).to_numpy(bool)
        z_rmse, z_se, lateral = _rmse(locs[checked & locs["in_range"].to_numpy(bool)], truth)
        right = right or {"z": z_rmse, "lateral": lateral}
        out.append({
            "astigmatism": kind, "seed": seed, "calibration": name,
            "median chi2": float(np.median(locs["consistency_chi2"][checked])),
            "axis °": f"{found.axis_deg:+.1f} ± {found.axis_se_deg:.1f}",
            "axis χ² gain": f"{found.axis_gain:.1f} ± {found.axis_gain_se:.1f}",
            "log width ratio": f"{found.log_width:+.3f} ± {found.log_width_se:.3f}",
            "blur nm": f"{found.blur_nm:+.0f} ± {_blur_se_nm(found):.0f}",
            "warns": "yes" if caught else "no",
            "good of correct in range": float(locs["good"].to_numpy(bool)[located].mean()),
            "z RMSE nm": f"{z_rmse:.0f} ± {z_se:.0f}",
            "z RMSE / right's": z_rmse / right["z"],
            "lateral RMSE nm (right's)": f"{lateral:.1f} ({right['lateral']:.1f})",
            "axis off, 20/40/80 spots %": _small_tables(locs[checked], cal, seed)
            if name == "right" else "",
        })  # fmt: skip
    return out


def _rmse(spots: pd.DataFrame, truth: pd.DataFrame) -> tuple[float, float, float]:
    """RMS z error (nm) of ``spots`` against the nearest true molecule within 250 nm laterally,
    at any depth, after one z offset, its standard error, and the RMS lateral error (nm)."""
    pairs, _ = offset_pairs(truth, spots, axial_nm=1e6)
    square = pairs["dz_nm"].to_numpy() ** 2
    rmse = float(np.sqrt(np.mean(square)))
    se = rmse * np.std(square) / (2 * np.mean(square) * np.sqrt(square.size))
    return rmse, float(se), float(np.sqrt(np.mean(pairs["dx_nm"] ** 2 + pairs["dy_nm"] ** 2)))


def _small_tables(spots: pd.DataFrame, cal: Calibration, seed: int) -> str:
    """Percent of :data:`SUBSETS` random draws of each of :data:`SMALL_TABLES` of ``spots``
    whose axis :func:`~latentz.localization.mismatch.calibration_mismatch` finds off."""
    rng = np.random.default_rng(seed)
    shares = []
    for size in SMALL_TABLES:
        draws = (spots.iloc[rng.choice(len(spots), size, replace=False)] for _ in range(SUBSETS))
        off = [mismatch.calibration_mismatch(draw, cal).axis_off for draw in draws]
        shares.append(100 * np.mean(off))
    return "/".join(f"{share:.0f}" for share in shares)


def _blur_se_nm(found: mismatch.Mismatch) -> float:
    """The blur's standard error as a σ (nm) at its value."""
    return found.blur_se_nm2 / (2 * max(abs(found.blur_nm), 1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--right", type=int, default=3, help="more microscopes of each kind")
    parser.add_argument("--start", type=int, default=1,
                        help="the first of them: seed + 100 x start")  # fmt: skip
    parser.add_argument("--kinds", nargs="+", choices=list(MICROSCOPES), default=list(MICROSCOPES),
                        help="the kinds of astigmatism to run")  # fmt: skip
    args = parser.parse_args()
    started, start = machine(), time.perf_counter()
    chosen = {kind: MICROSCOPES[kind] for kind in args.kinds}
    draws = [(kind, seed, astig, False) for kind, (seed, astig) in chosen.items()]
    draws += [(kind, seed + 100 * k, astig, True) for kind, (seed, astig) in chosen.items()
              for k in range(args.start, args.start + args.right)]  # fmt: skip
    rows = [r for draw in draws for r in scores(*draw)]
    notes = (
        f"The calibration is blamed when the axis lies more than {mismatch.AXIS_LIMIT_DEG:g}° off "
        f"and that turn gains χ² by more than {mismatch.AXIS_GAIN_SIGNIFICANCE:g} standard errors, "
        f"the log width ratio above {mismatch.LOG_WIDTH_LIMIT:g} or the blur beyond "
        f"{mismatch.BLUR_LIMIT_NM:g} nm, by more than {mismatch.SIGNIFICANCE:g} standard errors; "
        "median chi2 over the converged, unique spots. Took "
        f"{time.perf_counter() - start:.0f} s on a loaded machine."
    )
    table = markdown(pd.DataFrame(rows))
    name = "bench_wrong_calibration" + (f"_start{args.start}" if args.start != 1 else "")
    write_results(f"{name}.md", "Wrong calibrations", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

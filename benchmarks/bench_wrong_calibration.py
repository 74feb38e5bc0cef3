"""The wrong-calibration test against truth: its statistic on right and on wrong calibrations.

For one random astigmatic microscope with strong (50-90 nm RMS) and one with weak (20-30 nm RMS)
astigmatism (:func:`latentz.simulate.molecules.random_microscope`), molecules of 1,000-10,000
photons within ±400 nm at 0.5 per µm² are localized with calibrations made, with defaults, on
simulated 100 nm beads (:func:`latentz.validation.molecules.bead_calibration`) of: the same
microscope (right), and microscopes that differ in one thing: the astigmatism's axis turned by
90° or 45°, the pixel size 1.25x, the wavelength 1.2x. For each: the median
``consistency_chi2``, width ratio and axis mismatch of the converged, unique spots, whether
:func:`latentz.localization.quality.check_calibration_fits` warns, and the share of the correct,
in-range localizations that are good. Writes ``results/bench_wrong_calibration.md``.

Run: ``python benchmarks/bench_wrong_calibration.py``.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_verdicts import markdown

from latentz.localization import quality
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.molecules import Microscope, random_microscope
from latentz.validation.molecules import bead_calibration, localized_molecules

MICROSCOPES = {"strong": (11, (50.0, 90.0)), "weak": (12, (20.0, 30.0))}


def variants(microscope: Microscope) -> dict[str, Microscope]:
    """The microscope and its one-change variants whose beads make the wrong calibrations."""
    optics, aberrations, camera = microscope
    c = dict(zip(aberrations.modes, aberrations.coefficients_nm[:, 0], strict=True))
    field = aberrations.field_shape
    return {
        "right": microscope,
        "axis 90° off": microscope._replace(
            aberrations=AberrationMap.constant({**c, 5: -c[5], 6: -c[6]}, field_shape=field)
        ),
        "axis 45° off": microscope._replace(
            aberrations=AberrationMap.constant({**c, 5: -c[6], 6: c[5]}, field_shape=field)
        ),
        "pixel size 1.25x": microscope._replace(
            optics=dataclasses.replace(optics, magnification=optics.magnification / 1.25)
        ),
        "wavelength 1.2x": microscope._replace(
            optics=dataclasses.replace(optics, wavelength_nm=optics.wavelength_nm * 1.2)
        ),
    }


def scores(kind: str, seed: int, astigmatism: tuple[float, float]) -> list[dict]:
    rng = np.random.default_rng(seed)
    microscope = random_microscope(rng, astigmatism_nm=astigmatism)
    out = []
    for name, source in variants(microscope).items():
        cal = bead_calibration(source, seed)
        locs, _, _ = localized_molecules(
            microscope, cal, np.random.default_rng(seed + 1), density_per_um2=0.5, n_frames=6,
            photons=(1e3, 1e4), z_range_nm=(-400.0, 400.0),
        )  # fmt: skip
        checked = (
            locs["converged"] & ~locs["duplicate"] & np.isfinite(locs["consistency_chi2"])
        ).to_numpy(bool)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            quality.check_calibration_fits(locs)
        located = (locs["correct"] & locs["in_range"]).to_numpy(bool)
        out.append({
            "astigmatism": kind, "calibration": name,
            "median chi2": float(np.median(locs["consistency_chi2"][checked])),
            "width ratio": float(np.median(locs["width_ratio"][checked])),
            "axis mismatch": float(np.median(locs["axis_mismatch"][checked])),
            "warns": "yes" if caught else "no",
            "good of correct in range": float(locs["good"].to_numpy(bool)[located].mean()),
        })  # fmt: skip
    return out


def main() -> None:
    started, start = machine(), time.perf_counter()
    rows = [r for kind, (seed, astig) in MICROSCOPES.items() for r in scores(kind, seed, astig)]
    notes = (
        f"Median over the converged, unique spots; the calibration is blamed above a median "
        f"chi2 of {quality.MISMATCH_MEDIAN_CHI2:g}. Took {time.perf_counter() - start:.0f} s "
        "on a loaded machine."
    )
    table = markdown(pd.DataFrame(rows))
    write_results("bench_wrong_calibration.md", "Wrong calibrations", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

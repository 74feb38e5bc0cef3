"""Dim molecules against truth: detection, and x, y, z precision against the Cramér–Rao bound.

For ``--microscopes`` random astigmatic microscopes (:func:`latentz.simulate.molecules.
random_microscope`, seeds from ``--seed``), each calibrated with defaults on its own simulated
100 nm beads (:func:`latentz.validation.molecules.bead_calibration`), ``--frames`` frames of
128 x 128 px hold sparse molecules (0.1 per µm²) of 300–3,000 photons (log-uniform) within
±400 nm over ``--background`` photoelectrons per pixel, localized with defaults
(:func:`latentz.validation.molecules.precision_against_bounds`). By photons, over the isolated
molecules (no other within 12 px): the share found (a localization within 2 px) and good; the
RMS error and its robust twin (1.4826 MAD) in units of the Cramér–Rao bound of the five-parameter
model (x, y, photons, background, z through the calibration curves,
:func:`latentz.validation.bounds.localization_bounds`, at the fitted z), the median bound, and
how often the reported 1σ covers the error, and the localizations that are no molecule's.
Beside latentz's z, the same for the yardstick :func:`latentz.validation.bounds.curves_fit_z`
(``z curves``: z fitted by maximum likelihood through the calibration curves, which latentz does
not do) over the same molecules (``both``), and the errors against the physical bound of each
molecule, its microscope's own PSF (``PSF bound``, :func:`latentz.validation.bounds.
psf_bounds`). ``--threshold`` sets the detection threshold. Writes
``results/bench_dim.md`` (``bench_dim_threshold_<t>.md``).

Run: ``python benchmarks/bench_dim.py``.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_edges import microscope_parser
from bench_verdicts import markdown

from latentz.simulate.molecules import random_microscope
from latentz.validation.molecules import bead_calibration, precision_against_bounds

PHOTON_BANDS = (300, 500, 700, 1000, 1500, 3000)


def summary(errors: pd.DataFrame) -> list[dict]:
    """One row per photon band of the isolated molecules."""
    out = []
    for low, high in zip(PHOTON_BANDS[:-1], PHOTON_BANDS[1:], strict=True):
        band = errors[errors["isolated"] & (errors["photons"] >= low) & (errors["photons"] < high)]
        seen = band[np.isfinite(band["z_nm"])]
        row = {"photons": f"{low}–{high}", "molecules": len(band), "found": band["found"].mean(),
               "good": band["good"].mean()}  # fmt: skip
        for axis in "xz":
            ratio = seen[f"{axis}_nm"] / seen[f"{axis}_crlb_nm"]
            row[f"{axis} RMS / CRLB"] = float(np.sqrt(np.mean(ratio**2)))
            row[f"{axis} robust / CRLB"] = float(1.4826 * np.median(np.abs(ratio)))
            row[f"{axis} CRLB nm"] = float(np.median(seen[f"{axis}_crlb_nm"]))
            row[f"{axis} median σ / CRLB"] = float(
                np.median(seen[f"{axis}_err_nm"] / seen[f"{axis}_crlb_nm"])
            )
            row[f"{axis} 1σ covers"] = float(
                np.mean(np.abs(seen[f"{axis}_nm"]) < seen[f"{axis}_err_nm"])
            )
        both = seen[np.isfinite(seen["z_curves_nm"])]
        for name, column in (("z", "z_nm"), ("z curves", "z_curves_nm")):
            ratio = both[column] / both["z_crlb_nm"]
            row[f"{name} robust / CRLB, both"] = float(1.4826 * np.median(np.abs(ratio)))
            row[f"{name} RMS / CRLB, both"] = float(np.sqrt(np.mean(ratio**2)))
        row["z PSF bound nm"] = float(np.median(seen["z_psf_crlb_nm"]))
        for name, column in (("x", "x_nm"), ("z", "z_nm"), ("z curves", "z_curves_nm")):
            ratio = both[column] / both[f"{name[0]}_psf_crlb_nm"]
            row[f"{name} robust / PSF bound, both"] = float(1.4826 * np.median(np.abs(ratio)))
        out.append(row)
    return out


def main() -> None:
    parser = microscope_parser(__doc__, frames=30)
    parser.add_argument("--threshold", type=float, help="detection threshold (noise units)")
    parser.add_argument("--background", type=float, default=20.0)
    args = parser.parse_args()
    started, start = machine(), time.perf_counter()
    every = []
    for seed in range(args.seed, args.seed + args.microscopes):
        rng = np.random.default_rng(seed)
        microscope = random_microscope(rng)
        calibration = bead_calibration(microscope, seed)
        every.append(precision_against_bounds(
            microscope, calibration, rng, n_frames=args.frames, background=args.background,
            threshold=args.threshold, photons=(300.0, 3000.0), z_range_nm=(-400.0, 400.0),
            yardsticks=True,
        ))  # fmt: skip
    table = markdown(pd.DataFrame(summary(pd.concat(every, ignore_index=True))))
    unmatched = sum(e.attrs["unmatched"] for e in every) / (args.microscopes * args.frames)
    threshold = "localize's default" if args.threshold is None else f"{args.threshold:g}"
    notes = (
        f"{args.microscopes} microscopes, background {args.background:g} photoelectrons per "
        f"pixel, detection threshold {threshold}: {unmatched:.2f} localizations per frame are "
        "no molecule's nearest within 2 px (false detections and duplicates). A right 1σ covers "
        "68.3 %; an efficient estimator's RMS / CRLB is 1. "
        f"Took {time.perf_counter() - start:.0f} s on a loaded machine."
    )
    suffix = "" if args.threshold is None else f"_threshold_{args.threshold:g}"
    write_results(f"bench_dim{suffix}.md", "Dim molecules", started, notes, table)
    print(notes, table, sep="\n\n")


if __name__ == "__main__":
    main()

"""Benchmark: point emitters read through a calibration on beads, with and without their diameter.

The validation microscope (:mod:`latentz.validation`: scalar pupil, 65 nm RMS oblique
astigmatism with field-dependent aberrations, a curved focal surface, a tilted substrate), beads
rendered as uniform balls (:func:`latentz.validation.microscope.bead_slices`). For each NA one
study of 49 beads of 2·10⁵ photons in one through-focus stack over a 160² px field, and point
test emitters of 5·10³–5·10⁴ photons in 10 frames at random z, simulated once per bead size with
one seed: every study has the same bead places, so the calibrations differ only in the beads'
size (and the noise). Each calibration (``shape="auto"``, fixed ROI, each field model asked for;
or every choice left to ``calibrate`` with ``--defaults``) reads the point study's test frames,
scored by :func:`latentz.validation.truth.score` (one plane removed) over the in-range spots:
z RMSE, the mean z error in each quarter of the test z range (bias, from below focus to above),
the share of spots within their reported 1σ, and the RMS of each spot's z error less its error
through the point particles' calibration of the same settings (the part the beads' size adds).
Writes ``results/bench_bead_size.md``.

With ``--simulator``, latentz's own simulator instead: a random high-NA microscope
(:func:`latentz.simulate.molecules.random_microscope`), six beads of 10⁵ photons through ±1 µm
(200 nm, or 1 nm for points), calibrated with defaults, and molecules of 3·10³–3·10⁴ photons
within ±400 nm (8 frames at 0.5 per µm²): z RMSE of the converged in-range molecules against the
nearest true molecule (one offset removed), their share that is ``good``, and the blur of
``localize``'s wrong-calibration check (:mod:`latentz.localization.mismatch`). Writes
``results/bench_bead_size_simulator.md``.

Run: ``python benchmarks/bench_bead_size.py [--defaults] [--simulator]``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz.calibration import Calibration, calibrate
from latentz.camera import Camera
from latentz.localization.mismatch import calibration_mismatch
from latentz.simulate.molecules import random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.datasets import ValidationData, simulate_study
from latentz.validation.fields import AberrationFields
from latentz.validation.microscope import Microscope
from latentz.validation.molecules import bead_calibration, localized_molecules
from latentz.validation.truth import localize_test, score, summary

HERE = Path(__file__).resolve().parent
#: Per NA: immersion index, pixel (nm), the calibration's z half range and step, the test
#: emitters' z half range (nm), the fixed ROI (px) and the bead diameters (nm).
CASES = {
    1.4: {"n_medium": 1.518, "px": 100.0, "z_half": 1500.0, "z_step": 25.0, "test_half": 800.0,
          "roi": 13, "beads": (200.0, 100.0)},
    0.55: {"n_medium": 1.0, "px": 130.0, "z_half": 3000.0, "z_step": 50.0, "test_half": 2000.0,
           "roi": 17, "beads": (200.0,)},
}  # fmt: skip


def study(na: float, bead_nm: float, seed: int) -> ValidationData:
    """The study of ``na`` with beads of ``bead_nm`` (0: points)."""
    case = CASES[na]
    layout = {"field_px": 160, "grid": 7, "n_stacks": 1, "z_half_nm": case["z_half"],
              "z_step_nm": case["z_step"], "photons": 2e5, "n_test": 40, "n_frames": 10,
              "test_half_nm": case["test_half"], "patch_px": 23}  # fmt: skip
    px = case["px"]
    return simulate_study(
        layout,
        Microscope(na=na, n_medium=case["n_medium"], pixel_size_nm=px),
        AberrationFields.random((160, 160), seed=seed, pixel_size_nm=px),
        Camera(offset=100.0, gain=0.5, readnoise=1.5, pixel_size_nm=px),
        np.random.default_rng(seed),
        background=2.0,
        bead_nm=bead_nm,
        test_photons=(5e3, 5e4),
    )


def scored(test: ValidationData, cal: Calibration) -> pd.DataFrame:
    """:func:`~latentz.validation.truth.score` of ``cal`` on ``test``'s frames."""
    return score(test, cal.apply(localize_test(test, calibration=cal)))


def figures(errors: pd.DataFrame, points: pd.DataFrame, half_nm: float) -> dict:
    """z RMSE, bias by quarter of the test z range (±``half_nm``) and 1σ coverage of the
    in-range spots of ``errors``, and the RMS of their z error less that of the same spots read
    through the point particles' calibration (``points``), in nm."""
    used = errors[errors["in_range"].to_numpy(bool)]
    quarter = np.clip(((used["true_z_nm"].to_numpy() + half_nm) / half_nm * 2).astype(int), 0, 3)
    error = used["err_z_nm"].to_numpy()
    key = ["emitter", "frame"]
    alone = [t.drop_duplicates(key, keep=False) for t in (used, points[points["in_range"]])]
    both = alone[0].merge(alone[1], on=key, suffixes=("", "_p"))
    shift = both["err_z_nm"].to_numpy() - both["err_z_nm_p"].to_numpy()
    table = summary(errors)
    return {"spots": int(table["spots"]), "z RMSE nm": round(table["rmse_z"], 1),
            "bias by quarter of z, nm": " / ".join(f"{error[quarter == q].mean():+.0f}"
                                                   for q in range(4)),
            "1σ covers z": f"{table['cover_z']:.0%}",
            "z − points' z, RMS nm": round(float(np.sqrt(np.mean(shift**2))), 1)}  # fmt: skip


def simulator_rows(seed: int) -> list[dict]:
    """The ``--simulator`` rows of microscope ``seed``: points, 200 nm beads as imaged and with
    their diameter."""
    microscope = random_microscope(np.random.default_rng(seed))
    optics = microscope[0]
    rows = []
    for bead, given in ((1.0, None), (200.0, None), (200.0, 200.0)):
        cal = bead_calibration(microscope, seed, bead_nm=bead, photons=1e5,
                               particle_diameter_nm=given)  # fmt: skip
        locs, truth, _ = localized_molecules(
            microscope, cal, np.random.default_rng(seed + 1), density_per_um2=0.5, n_frames=8,
            photons=(3e3, 3e4), z_range_nm=(-400.0, 400.0),
        )  # fmt: skip
        used = locs[locs["in_range"].to_numpy(bool) & locs["converged"].to_numpy(bool)]
        pairs, _ = offset_pairs(truth, used, axial_nm=1e6)
        rows.append({"NA": round(optics.na, 2), "px nm": round(optics.pixel_size_nm),
                     "particles": "200 nm beads" if bead > 1 else "points (1 nm)",
                     "diameter given": f"{given:.0f} nm" if given else "",
                     "molecules": len(pairs),
                     "z RMSE nm": round(float(np.sqrt(np.mean(pairs["dz_nm"] ** 2))), 1),
                     "good": f"{locs['good'].mean():.0%}",
                     "blur nm": round(calibration_mismatch(locs, cal).blur_nm, 1)})  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def write(name: str, title: str, rows: list[dict]) -> None:
    """Print ``rows`` as a table and write it to ``results/{name}.md`` under ``title``."""
    text = pd.DataFrame(rows).to_markdown(index=False)
    print(text)
    write_text_atomic(
        HERE / "results" / f"{name}.md",
        f"# {title}\n\n`python benchmarks/bench_bead_size.py {' '.join(sys.argv[1:])}` (see the "
        "module docstring)\n\n" + text + "\n",
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--field-models", default="curves,nearest")
    parser.add_argument(
        "--defaults",
        action="store_true",
        help="also NA 1.4's 200 nm beads with every choice left to calibrate",
    )
    parser.add_argument("--simulator", action="store_true",
                        help="latentz's simulator instead (module notes)")  # fmt: skip
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    if args.simulator:
        title = "Molecules read through bead calibrations, latentz's simulator"
        write("bench_bead_size_simulator", title, simulator_rows(3))
        return
    rows = []
    for na, case in CASES.items():
        test = study(na, 0.0, args.seed)
        stacks = {0.0: test} | {b: study(na, b, args.seed) for b in case["beads"]}
        runs = [(0.0, None)] + [(b, given) for b in case["beads"] for given in (None, b)]
        fixed = {"shape": "auto", "roi_size": case["roi"]}
        settings = [{**fixed, "field_model": m} for m in args.field_models.split(",")]
        if args.defaults and na == 1.4:
            settings.append({})
        for options in settings:
            points = None
            for bead, given in runs:
                if not options and bead == 100.0:
                    continue
                data = stacks[bead]
                cal = calibrate(data.stacks, data.z_nm, camera=data.camera,
                                particle_diameter_nm=given, **options)  # fmt: skip
                errors = scored(test, cal)
                points = errors if points is None else points
                row = {"NA": na, "particles": f"{bead:.0f} nm beads" if bead else "points",
                       "diameter given": f"{given:.0f} nm" if given else "",
                       "choices": "fixed" if options else "defaults", "ROI px": cal.roi_size,
                       "shape": cal.shape, "field model": cal.field_model}  # fmt: skip
                rows.append(row | figures(errors, points, case["test_half"]))
                print(rows[-1], flush=True)
    write("bench_bead_size", "Point emitters read through bead calibrations", rows)


if __name__ == "__main__":
    main()

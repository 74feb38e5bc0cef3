"""A 3D STORM-like movie against truth: molecules on filaments, calibrated on a short bead stack.

The nearest simulated likeness of a recorded astigmatic STORM movie calibrated with defaults on a
bead stack of the same microscope: :func:`latentz.simulate.molecules.random_microscope` at 65 nm
pixels with weak (8-20 nm RMS) or very weak (3-8 nm RMS) astigmatism; six 100 nm beads of 2e4
photons imaged over ±400 nm in 10 nm steps, calibrated with defaults; molecules of 1e3-1e4
photons, about 8 per frame on six random straight filaments (z varying slowly along each, within
about ±400 nm), 120 frames of 128 x 128 px over 40 photoelectrons of background. With
``--spherical``, the molecules (not the beads) carry that much more spherical aberration (Z11, nm
RMS), as depth in an aqueous sample adds. Truth is where each molecule was put; localizations are
paired with it as the challenge does (:func:`latentz.validation.challenge.offset_pairs`, one z
offset removed).

Per microscope: the shape and ROI ``calibrate`` chose, whether the wrong-calibration warning fires,
the width check's blur (nm), the z RMSE and the share of errors within the reported 1σ for
molecules of 1e3-3e3 and 3e3-1e4 photons (paired rows in range, true |z| ≤ 300 nm), and the share
of the correct localizations within ±300 nm that are good and that are ``out_of_range``.

Run: ``python benchmarks/bench_storm_like.py [--seeds 1 2 3] [--astigmatism 8,20 3,8]
[--spherical 0 40]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np
import pandas as pd
from _rounds import machine, write_results
from bench_verdicts import markdown

from latentz.localization import localize, mismatch
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.molecules import Microscope, molecule_frames, random_microscope
from latentz.validation.challenge import offset_pairs
from latentz.validation.molecules import bead_calibration

FIELD_PX = 128
PIXEL_NM = 65.0
FRAMES = 120
INSIDE_NM = 300.0


def microscope(rng: np.random.Generator, astigmatism_nm: tuple[float, float]) -> Microscope:
    """A random astigmatic microscope of ``astigmatism_nm`` RMS, at 65 nm pixels."""
    found = random_microscope(rng, astigmatism_nm=astigmatism_nm)
    optics = dataclasses.replace(found.optics, magnification=6500.0 / PIXEL_NM)
    camera = dataclasses.replace(found.camera, pixel_size_nm=PIXEL_NM)
    return found._replace(optics=optics, camera=camera)


def with_spherical(scope: Microscope, extra_nm: float) -> Microscope:
    """``scope`` with ``extra_nm`` more spherical aberration (Z11, nm RMS)."""
    modes = dict(zip(scope.aberrations.modes, scope.aberrations.coefficients_nm[:, 0], strict=True))
    modes[11] = modes.get(11, 0.0) + extra_nm
    field = scope.aberrations.field_shape
    return scope._replace(aberrations=AberrationMap.constant(modes, field_shape=field))


def filaments(rng: np.random.Generator) -> pd.DataFrame:
    """Molecules on six random straight filaments: ``frame, x, y`` (px), ``z_nm``, ``photons``."""
    lines = [(rng.uniform(0, FIELD_PX, 2), rng.uniform(0, np.pi), rng.uniform(-200, 200),
              rng.uniform(50, 200), rng.uniform(30, 120)) for _ in range(6)]  # fmt: skip
    rows = []
    for frame in range(FRAMES):
        for _ in range(rng.poisson(8)):
            start, angle, z0, amplitude, period = lines[rng.integers(6)]
            s = rng.uniform(-FIELD_PX, FIELD_PX)
            x = start[0] + s * np.cos(angle) + rng.normal(0, 0.4)
            y = start[1] + s * np.sin(angle) + rng.normal(0, 0.4)
            if -0.5 < x < FIELD_PX - 0.5 and -0.5 < y < FIELD_PX - 0.5:
                photons = np.exp(rng.uniform(np.log(1e3), np.log(1e4)))
                rows.append((frame, x, y, z0 + amplitude * np.sin(s / period), photons))
    return pd.DataFrame(rows, columns=["frame", "x", "y", "z_nm", "photons"])


def one(seed: int, astigmatism_nm: tuple[float, float], spherical_nm: float) -> dict:
    rng = np.random.default_rng(seed)
    scope = microscope(rng, astigmatism_nm)
    cal = bead_calibration(scope, seed, field_shape=(FIELD_PX, FIELD_PX),
                           z_nm=np.arange(-400.0, 400.1, 10.0))  # fmt: skip
    frames, truth = molecule_frames(
        filaments(rng), with_spherical(scope, spherical_nm),
        n_frames=FRAMES, frame_shape=(FIELD_PX, FIELD_PX), background=40.0, seed=seed,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU note; the verdicts are read from the table
        locs = localize(frames, calibration=cal)
    found = mismatch.calibration_mismatch(locs, cal)  # what localize's check measured
    pairs, _ = offset_pairs(truth, locs)
    rows = locs.loc[pairs["locs_row"].to_numpy()]
    inside = np.abs(truth.loc[pairs["truth_row"].to_numpy(), "z_nm"].to_numpy()) <= INSIDE_NM
    photons = truth.loc[pairs["truth_row"].to_numpy(), "photons"].to_numpy()
    dz, sigma = pairs["dz_nm"].to_numpy(), rows["z_err_nm"].to_numpy()
    scored = inside & rows["in_range"].to_numpy(bool) & np.isfinite(dz)
    row = {
        "astigmatism nm": f"{astigmatism_nm[0]:g}-{astigmatism_nm[1]:g}", "seed": seed,
        "extra Z11 nm": spherical_nm, "ROI / shape": f"{cal.roi_size} / {cal.shape}",
        "warns": "yes" if found.axis_off or found.widths_off else "no",
        "blur nm": round(found.blur_nm),
    }  # fmt: skip
    for low, high in ((1e3, 3e3), (3e3, 1e4)):
        part = scored & (photons >= low) & (photons < high)
        label = f"{low:.0e}-{high:.0e}".replace("e+0", "e")
        row[f"z RMSE nm {label}"] = float(np.sqrt(np.mean(dz[part] ** 2)))
        row[f"1σ covers {label}"] = float(np.mean(np.abs(dz[part]) <= sigma[part]))
    row["good of correct"] = float(rows["good"].to_numpy(bool)[inside].mean())
    row["out of range of correct"] = float(rows["out_of_range"].to_numpy(bool)[inside].mean())
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--astigmatism", nargs="+", default=["8,20", "3,8"],
                        help="RMS astigmatism ranges (nm), e.g. 8,20")  # fmt: skip
    parser.add_argument("--spherical", type=float, nargs="+", default=[0.0, 40.0],
                        help="the molecules' extra spherical aberration (nm RMS)")  # fmt: skip
    args = parser.parse_args()
    started = machine()
    table = pd.DataFrame([
        one(seed, tuple(float(v) for v in astigmatism.split(",")), spherical)
        for astigmatism in args.astigmatism for seed in args.seeds for spherical in args.spherical
    ])  # fmt: skip
    text = markdown(table)
    print(text)
    write_results("bench_storm_like.md", "A 3D STORM-like movie against truth", started,
                  __doc__.split("\n\n")[1].replace("\n", " "), text)  # fmt: skip


if __name__ == "__main__":
    main()

"""Single-molecule truth: a bead calibration of a simulated SMLM microscope, its molecules
localized, and each localization scored against where the simulation put the molecules.

Used by the tests and ``benchmarks/bench_verdicts.py`` to measure the quality verdicts. The
frames come from :mod:`latentz.simulate.molecules`; a localization is correct when the
challenge's one-to-one matching (:func:`latentz.validation.challenge.correct_rows`) pairs it with
a true molecule.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from latentz.calibration import Calibration, calibrate
from latentz.localization import localize
from latentz.simulate import calibration_dataset
from latentz.simulate.molecules import Microscope, molecule_frames, place_molecules
from latentz.validation.challenge import correct_rows

__all__ = ["bead_calibration", "localized_molecules", "true_positives"]

#: One set: (localizations with ``correct``, truth, calibration).
Scored = tuple[pd.DataFrame, pd.DataFrame, Calibration]


def bead_calibration(
    microscope: Microscope, seed: int, *, field_shape: tuple[int, int] = (128, 128)
) -> Calibration:
    """``calibrate`` with defaults on six 100 nm beads (20,000 photons, background 20) of
    ``microscope``, imaged from −1 to +1 µm in 25 nm steps."""
    optics, aberrations, camera = microscope
    data = calibration_dataset(
        n_particles=6, z_nm=np.arange(-1000.0, 1000.1, 25.0), n_stage_positions=1,
        frame_shape=field_shape, particle_diameter_nm=100.0, diameter_sd_nm=5.0, photons=2e4,
        background=20.0, optics=optics, aberrations=aberrations, camera=camera,
        min_spacing_px=35.0, tilt_mrad=0.0, seed=seed,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU and the nearest-particle field model notes
        return calibrate(list(data.stacks), data.z_nm, camera=camera)


def localized_molecules(
    microscope: Microscope,
    calibration: Calibration,
    rng: np.random.Generator,
    *,
    density_per_um2: float,
    n_frames: int,
    field_shape: tuple[int, int] = (128, 128),
    **placement,
) -> Scored:
    """Molecules of ``microscope`` (:func:`~latentz.simulate.molecules.place_molecules` with
    ``placement``) localized with ``calibration`` and defaults, each row marked ``correct``."""
    molecules = place_molecules(
        rng, n_frames=n_frames, frame_shape=field_shape,
        pixel_nm=microscope.optics.pixel_size_nm, density_per_um2=density_per_um2, **placement,
    )  # fmt: skip
    frames, truth = molecule_frames(
        molecules, microscope, n_frames=n_frames, frame_shape=field_shape,
        seed=int(rng.integers(2**31)),
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU note; the verdicts are read from the table
        locs = localize(frames, calibration=calibration)
    correct, _ = correct_rows(truth, locs)
    return locs.assign(correct=correct), truth, calibration


def true_positives(
    sets: Sequence[tuple[pd.DataFrame, pd.DataFrame]],
    keep: Callable[[pd.DataFrame], np.ndarray] | None = None,
) -> int:
    """Localizations matched to a true molecule, over all (localizations, truth) ``sets``, of
    the rows ``keep(locs)`` keeps (all rows by default), matched afresh: when a flag drops one
    of two fits of a molecule, the other may take its place."""
    total = 0
    for locs, truth, *_ in sets:
        rows = locs if keep is None else locs[keep(locs)]
        total += int(correct_rows(truth, rows)[0].sum())
    return total

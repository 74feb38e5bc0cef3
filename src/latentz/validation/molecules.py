"""Single-molecule truth: a bead calibration of a simulated SMLM microscope, its molecules
localized, and each localization scored against where the simulation put the molecules.

Used by the tests and ``benchmarks/bench_verdicts.py`` to measure the quality verdicts. The
frames come from :mod:`latentz.simulate.molecules`; a localization is correct when the
challenge's one-to-one matching (:func:`latentz.validation.challenge.correct_rows`) pairs it with
a true molecule, each measurement counted once (:func:`one_per_measurement`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.calibration import Calibration, calibrate
from latentz.detect import cut_rois
from latentz.localization import localize
from latentz.simulate import calibration_dataset
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.molecules import (
    Microscope,
    molecule_frames,
    place_edge_molecules,
    place_molecules,
)
from latentz.validation.bounds import curves_fit_z, localization_bounds, psf_bounds
from latentz.validation.challenge import correct_rows

__all__ = [
    "bead_calibration",
    "edge_errors",
    "localized_molecules",
    "nearest_rows",
    "one_per_measurement",
    "precision_against_bounds",
    "true_positives",
    "with_calibration_of",
    "wrong_microscopes",
]

#: One set: (localizations with ``correct``, truth, calibration).
Scored = tuple[pd.DataFrame, pd.DataFrame, Calibration]


def bead_calibration(
    microscope: Microscope,
    seed: int,
    *,
    field_shape: tuple[int, int] = (128, 128),
    roi_size: int | None = None,
    z_nm: np.ndarray | None = None,
    bead_nm: float = 100.0,
    photons: float = 2e4,
    particle_diameter_nm: float | None = None,
) -> Calibration:
    """``calibrate`` with defaults (or the given ``roi_size``, px, and ``particle_diameter_nm``)
    on six beads of ``bead_nm`` (s.d. a tenth of it, at most 5 nm) and ``photons`` each
    (background 20) of ``microscope``, imaged at the stage positions ``z_nm`` (nm; from −1 to
    +1 µm in 25 nm steps if None)."""
    optics, aberrations, camera = microscope
    if z_nm is None:
        z_nm = np.arange(-1000.0, 1000.1, 25.0)
    data = calibration_dataset(
        n_particles=6, z_nm=z_nm, n_stage_positions=1,
        frame_shape=field_shape, particle_diameter_nm=bead_nm,
        diameter_sd_nm=min(5.0, bead_nm / 10), photons=photons, background=20.0, optics=optics,
        aberrations=aberrations, camera=camera,
        min_spacing_px=35.0, tilt_mrad=0.0, seed=seed,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU and the nearest-particle field model notes
        return calibrate(list(data.stacks), data.z_nm, camera=camera, roi_size=roi_size,
                         particle_diameter_nm=particle_diameter_nm)  # fmt: skip


def wrong_microscopes(microscope: Microscope) -> dict[str, Microscope]:
    """``microscope`` (as "right") and its variants that differ in one thing, whose beads make
    wrong calibrations: the astigmatism's axis turned by 90° or 45°, the pixel size 1.25x (the
    magnification over 1.25), the wavelength 1.2x."""
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


def with_calibration_of(microscope: Microscope, calibration_of: str, seed: int) -> Scored:
    """Molecules of ``microscope`` (0.5 per µm², 6 frames, 10³–10⁴ photons within ±400 nm)
    localized with a :func:`bead_calibration` of its variant ``calibration_of`` (a key of
    :func:`wrong_microscopes`: "right" for its own beads), both drawn from ``seed``: the
    experiment that tests a calibration against molecules it may not fit."""
    calibration = bead_calibration(wrong_microscopes(microscope)[calibration_of], seed)
    return localized_molecules(
        microscope, calibration, np.random.default_rng(seed + 1), density_per_um2=0.5,
        n_frames=6, photons=(1e3, 1e4), z_range_nm=(-400.0, 400.0),
    )  # fmt: skip


def true_positives(
    sets: Sequence[tuple[pd.DataFrame, pd.DataFrame]],
    keep: Callable[[pd.DataFrame], np.ndarray] | None = None,
) -> int:
    """Localizations matched to a true molecule, over all (localizations, truth) ``sets``, of
    the rows ``keep(locs)`` keeps (all rows by default), each measurement once
    (`one_per_measurement`), matched afresh: when a flag drops one of two fits of a molecule,
    the other may take its place."""
    total = 0
    for locs, truth, *_ in sets:
        rows = locs if keep is None else locs[keep(locs)]
        total += int(correct_rows(truth, rows[one_per_measurement(rows)])[0].sum())
    return total


def one_per_measurement(locs: pd.DataFrame) -> np.ndarray:
    """Which rows are measurements of their own: a fit that lies within the 1σ position error
    (``x_err`` and ``y_err`` in quadrature, px) of a more precise fit of its frame repeats it,
    as when several detections of one spot converge on the same optimum. The challenge's
    tolerances (250 nm laterally, 500 nm axially) would match each copy of a spot where
    molecules lie within a pixel of each other to one of them, and count one measurement as
    several correct localizations."""
    error = np.hypot(locs["x_err"].to_numpy(float), locs["y_err"].to_numpy(float))
    xy = locs[["x", "y"]].to_numpy(float)
    own = np.ones(len(locs), bool)
    for rows in locs.groupby("frame").indices.values():
        rows = rows[np.isfinite(xy[rows]).all(axis=1)]  # a fit without a position is its own
        rows = rows[np.argsort(error[rows], kind="stable")]  # the most precise first, NaN last
        if rows.size < 2:
            continue
        tree = cKDTree(xy[rows])
        for k, row in enumerate(rows):
            if own[row] and np.isfinite(error[row]):
                near = np.asarray(tree.query_ball_point(xy[row], error[row]), int)
                own[rows[near[near > k]]] = False
    return own


def edge_errors(
    microscope: Microscope,
    calibration: Calibration,
    rng: np.random.Generator,
    *,
    n_frames: int,
    frame_shape: tuple[int, int] = (96, 96),
    **placement,
) -> pd.DataFrame:
    """Molecules at the frame's edge (:func:`~latentz.simulate.molecules.place_edge_molecules`
    with ``placement``) localized with ``calibration`` and defaults, one row per molecule:
    ``distance_px``, ``across``, ``found`` (a localization within 2 px), its ``good`` and
    ``edge``, and its errors across the nearest edge, along it and in z (nm; one offset per
    axis, the inner molecules' median error, removed: a point molecule is not the calibration's
    bead) with their reported 1σ (``*_err_nm``)."""
    molecules = place_edge_molecules(rng, n_frames=n_frames, frame_shape=frame_shape, **placement)
    truth, found, row, _ = _localized_nearest(
        molecules, microscope, calibration, rng, n_frames=n_frames, frame_shape=frame_shape
    )
    cut_x = truth["across"].to_numpy() == 0
    inner = (truth["across"].to_numpy() == -1) & (row >= 0) & found["in_range"].to_numpy(bool)
    errors = {}
    for axis in "xyz":  # one offset per axis: the inner molecules' median error
        error = (found[f"{axis}_nm"] - truth[f"{axis}_nm"]).to_numpy()
        errors[axis] = error - np.median(error[inner])
    sigmas = {axis: found[f"{axis}_err_nm"].to_numpy() for axis in "xyz"}
    out = truth[["frame", "distance_px", "across", "photons"]].assign(
        found=row >= 0,
        good=found["good"].to_numpy(bool) & (row >= 0),
        edge=found["edge"].to_numpy(bool) & (row >= 0),
        across_nm=np.where(cut_x, errors["x"], errors["y"]),
        across_err_nm=np.where(cut_x, sigmas["x"], sigmas["y"]),
        along_nm=np.where(cut_x, errors["y"], errors["x"]),
        along_err_nm=np.where(cut_x, sigmas["y"], sigmas["x"]),
        z_nm=errors["z"],
        z_err_nm=sigmas["z"],
    )
    return out


def _localized_nearest(
    molecules: pd.DataFrame,
    microscope: Microscope,
    calibration: Calibration,
    rng: np.random.Generator,
    *,
    n_frames: int,
    frame_shape: tuple[int, int],
    background: float = 20.0,
    threshold: float | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray, np.ndarray]:
    """The truth of ``molecules`` imaged by ``microscope``, localized with ``calibration`` and
    defaults (detection ``threshold`` as given): (truth, the localization nearest each molecule,
    its position in the table or −1 where none lies within 2 px, the frames in ADU);
    ``attrs["rows"]`` of the second holds the number of localizations."""
    frames, truth = molecule_frames(
        molecules, microscope, n_frames=n_frames, frame_shape=frame_shape,
        background=background, seed=int(rng.integers(2**31)),
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CPU note
        locs = localize(frames, calibration=calibration, threshold=threshold)
    row = nearest_rows(truth, locs, radius_px=2.0)
    found = locs.iloc[np.maximum(row, 0)].reset_index(drop=True)
    found.attrs["rows"] = len(locs)
    return truth, found, row, frames


def nearest_rows(truth: pd.DataFrame, locs: pd.DataFrame, *, radius_px: float) -> np.ndarray:
    """For each true molecule, the position in ``locs`` of the nearest row of its frame within
    ``radius_px``, else −1."""
    nearest = np.full(len(truth), -1)
    frames = truth["frame"].to_numpy()
    for frame, rows in locs.groupby("frame").indices.items():
        mine = np.flatnonzero(frames == frame)
        dist, k = cKDTree(locs[["x", "y"]].to_numpy()[rows]).query(
            truth[["x", "y"]].to_numpy()[mine], distance_upper_bound=radius_px
        )
        nearest[mine] = np.where(np.isfinite(dist), rows[np.minimum(k, len(rows) - 1)], -1)
    return nearest


def precision_against_bounds(
    microscope: Microscope,
    calibration: Calibration,
    rng: np.random.Generator,
    *,
    n_frames: int,
    field_shape: tuple[int, int] = (128, 128),
    density_per_um2: float = 0.1,
    isolation_px: float = 12.0,
    background: float = 20.0,
    threshold: float | None = None,
    yardsticks: bool = False,
    **placement,
) -> pd.DataFrame:
    """Sparse molecules (:func:`~latentz.simulate.molecules.place_molecules` with
    ``placement``) localized with ``calibration`` and defaults, one row per molecule: its
    ``photons``, ``isolated`` (no other molecule within ``isolation_px``, none within 2 px of the
    frame's edge), ``found`` (a localization within 2 px) and that row's ``good``; its errors in
    x, y and z (nm, one offset per axis, the found isolated molecules' median error, removed),
    their reported 1σ (``*_err_nm``) and their Cramér–Rao bounds at the fitted z (``*_crlb_nm``,
    :func:`latentz.validation.bounds.localization_bounds`). Detection uses ``threshold``
    (default: localize's); ``attrs["unmatched"]`` counts the localizations that are no molecule's
    nearest within 2 px (false detections and duplicates). ``yardsticks``: also the z error of
    :func:`~latentz.validation.bounds.curves_fit_z` (``z_curves_nm``, its own offset removed;
    NaN where the ROI leaves the frame) and the physical bounds of the microscope's own PSF
    (``x_psf_crlb_nm``, ``y_psf_crlb_nm``, ``z_psf_crlb_nm``,
    :func:`~latentz.validation.bounds.psf_bounds`, in a window of the calibration's ROI)."""
    molecules = place_molecules(
        rng, n_frames=n_frames, frame_shape=field_shape,
        pixel_nm=microscope.optics.pixel_size_nm, density_per_um2=density_per_um2, **placement,
    )  # fmt: skip
    truth, found, row, frames = _localized_nearest(
        molecules, microscope, calibration, rng, n_frames=n_frames, frame_shape=field_shape,
        background=background, threshold=threshold,
    )  # fmt: skip
    out = truth[["frame", "photons", "z_nm"]].rename(columns={"z_nm": "true_z_nm"})
    out = out.assign(
        isolated=_isolated(truth, isolation_px, field_shape),
        found=row >= 0,
        good=found["good"].to_numpy(bool) & (row >= 0),
    )
    usable = out["found"].to_numpy() & out["isolated"].to_numpy() & found["in_range"].to_numpy()
    px = calibration.camera.pixel_size_nm
    bounds = localization_bounds(
        calibration, found["cal_particle"].to_numpy(), found["z_nm"].to_numpy(),
        truth["photons"].to_numpy(), background, readnoise=calibration.camera.readnoise,
    )  # fmt: skip
    for k, axis in enumerate("xyz"):
        error = (found[f"{axis}_nm"] - truth[f"{axis}_nm"]).to_numpy()
        out[f"{axis}_nm"] = np.where(usable, error - np.median(error[usable]), np.nan)
        out[f"{axis}_err_nm"] = np.where(usable, found[f"{axis}_err_nm"], np.nan)
        out[f"{axis}_crlb_nm"] = np.where(usable, bounds[:, k] * (px if axis != "z" else 1), np.nan)
    if yardsticks:
        z = _curves_fit_z(calibration, frames, found, usable) - truth["z_nm"].to_numpy()
        out["z_curves_nm"] = z - np.nanmedian(z)
        physical = np.full((len(truth), 3), np.nan)
        physical[usable] = psf_bounds(
            microscope, *(truth[c].to_numpy()[usable] for c in ("x", "y", "z_nm", "photons")),
            background, size=calibration.roi_size,
        )  # fmt: skip
        for k, axis in enumerate("xyz"):
            out[f"{axis}_psf_crlb_nm"] = physical[:, k] * (px if axis != "z" else 1)
    out.attrs["unmatched"] = found.attrs["rows"] - len(np.unique(row[row >= 0]))
    return out


def _curves_fit_z(
    calibration: Calibration, frames: np.ndarray, found: pd.DataFrame, rows: np.ndarray
) -> np.ndarray:
    """:func:`~latentz.validation.bounds.curves_fit_z` of the ``rows`` (bool) of ``found``
    whose ROI, centred on the nearest pixel, lies inside the frame; NaN elsewhere (nm)."""
    half = calibration.roi_size // 2
    col, line = (np.rint(found[c].to_numpy()).astype(int) for c in ("x", "y"))
    inside = (np.minimum(col, line) >= half) & (col < frames.shape[2] - half)
    rows = np.flatnonzero(rows & inside & (line < frames.shape[1] - half))
    out = np.full(len(found), np.nan)
    if not rows.size:
        return out
    rois = cut_rois(frames, found["frame"].to_numpy()[rows], line[rows] - half, col[rows] - half,
                    calibration.roi_size)  # fmt: skip
    start = found.iloc[rows][["x", "y", "amplitude", "background", "photons", "z_nm"]].to_numpy()
    start[:, 0] -= col[rows] - half
    start[:, 1] -= line[rows] - half
    out[rows] = curves_fit_z(calibration, calibration.camera.to_photons(rois),
                             found["cal_particle"].to_numpy()[rows], start)  # fmt: skip
    return out


def _isolated(truth: pd.DataFrame, radius_px: float, field_shape: tuple[int, int]) -> np.ndarray:
    """Molecules with no other of their frame within ``radius_px`` and 2 px or more inside."""
    out = np.zeros(len(truth), bool)
    xy = truth[["x", "y"]].to_numpy()
    for _, rows in truth.groupby("frame").indices.items():
        count = cKDTree(xy[rows]).query_ball_point(xy[rows], radius_px, return_length=True)
        out[rows] = count == 1
    inside = np.all((xy >= 2) & (xy <= np.array(field_shape[::-1]) - 3), axis=1)
    return out & inside

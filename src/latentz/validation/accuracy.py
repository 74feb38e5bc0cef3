"""Localization accuracy against simulated truth: the widefield study, the demo, the benchmarks.

A simulated sample of particles (a :class:`~latentz.simulate.CalibrationDataset` imaged at a few
piezo positions near focus) is localized as a user would localize it — detection and fits
(:func:`latentz.localization.localize`), then :meth:`Calibration.apply` — and every localization is
compared with the truth of its particle.

Truth, axially. The calibrated z axis has z = 0 on the calibration particles' surface of best
focus after removal of its plane of best fit (a substrate tilt and the planar part of the field
curvature cannot be told apart), so a spot's true z is its defocus minus that plane, fitted here
to the calibration particles' *true* best focus (:func:`focal_plane`).

Truth, laterally. ``"focus"``: where the particle appears at its own best focus, the paper's
definition of the actual lateral position (Fig. 2a), which is what the correction
``(x' − Δx', y' − Δy')`` restores. ``"geometric"``: where the particle is. They differ by the
apparent shift that aberrations (coma) cause in focus, a few nm that vary slowly and nearly
linearly across the field: a distortion, for the magnification and distortion calibration, not
for the z-dependent correction.

Errors are reported per spot; :func:`rmse` removes one global offset per axis first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = [
    "widefield_study",
    "score",
    "focal_plane",
    "localize_dataset",
    "focus_positions",
    "error_table",
    "rmse",
    "error_figure",
]


def focal_plane(truth: pd.DataFrame) -> np.ndarray:
    """``(c0, cx, cy)`` of the least-squares plane ``z = c0 + cx x + cy y`` (x, y in field
    pixels, z in nm) through the true best-focus defocus (``focus_defocus_nm``) of calibration
    particles (a :class:`~latentz.simulate.CalibrationDataset`'s ``truth``), fitted as the
    calibration's tilt plane (:class:`latentz.calibration.tilt.TiltPlane`)."""
    from latentz.calibration.tilt import TiltPlane

    plane = TiltPlane.from_estimate(
        truth["field_x"].to_numpy(float),
        truth["field_y"].to_numpy(float),
        truth["focus_defocus_nm"].to_numpy(float),
    )
    return np.array([plane.c0, plane.cx, plane.cy])


def localize_dataset(
    dataset: Any, *, roi_size: int, max_px: float = 2.0, **options: Any
) -> pd.DataFrame:
    """Detect and fit every stack of ``dataset``; keep the clean fits, in field pixels.

    Each spot is matched to the nearest true particle of its stack within ``max_px`` pixels and
    gets its ``particle`` and ``stack``; ``frame`` is the plane. Spots that did not converge, touch
    another or the frame's edge, or match no particle are dropped. ``options`` go to
    :func:`latentz.localization.localize`.
    """
    from latentz.localization import localize

    parts = []
    for k, (stack, origin) in enumerate(zip(dataset.stacks, dataset.origins, strict=True)):
        found = localize(stack, camera=dataset.camera, roi_size=roi_size, **options)
        found = found[found["converged"] & ~found["close_pair"] & ~found["edge"]]
        found = found.assign(x=found["x"] + origin[1], y=found["y"] + origin[0], stack=k)
        truth = dataset.truth[dataset.truth["stack"] == k]
        dist, idx = cKDTree(truth[["field_x", "field_y"]].to_numpy()).query(
            found[["x", "y"]].to_numpy()
        )
        near = dist <= max_px
        parts.append(found[near].assign(particle=truth["particle"].to_numpy()[idx[near]]))
    return pd.concat(parts, ignore_index=True)


def focus_positions(dataset: Any, *, roi_size: int) -> pd.DataFrame:
    """Apparent field position (pixels) of every particle at its own best focus.

    Each stack's particles are rendered without noise at their best-focus defocus and fitted
    in ROIs of ``roi_size`` centred on them, as calibration and ``localize`` place ROIs.
    Returns ``particle``, ``focus_x``, ``focus_y``.
    """
    from latentz.detect import cut_rois
    from latentz.fit import fit_rois
    from latentz.simulate import render_spots

    parts = []
    half = roi_size // 2
    for k, origin in enumerate(dataset.origins):
        truth = dataset.truth[dataset.truth["stack"] == k]
        frame_shape = dataset.stacks[k].shape[1:]
        image, _ = render_spots(
            pd.DataFrame(
                {"x": truth["x"], "y": truth["y"], "z_nm": truth["focus_defocus_nm"]}
            ).assign(photons=truth["photons"].to_numpy(), diameter_nm=truth["diameter_nm"]),
            frame_shape=frame_shape,
            origin=(int(origin[0]), int(origin[1])),
            optics=dataset.optics,
            aberrations=dataset.aberrations,
            background=dataset.background,
            noise=False,
        )
        cx = np.rint(truth["x"].to_numpy()).astype(int)
        cy = np.rint(truth["y"].to_numpy()).astype(int)
        inside = (cx >= half) & (cy >= half)
        inside &= (cx < frame_shape[1] - half) & (cy < frame_shape[0] - half)
        corner_x, corner_y = cx[inside] - half, cy[inside] - half
        rois = cut_rois(image, np.zeros(inside.sum(), int), corner_y, corner_x, roi_size)
        fit = fit_rois(rois)
        parts.append(
            pd.DataFrame(
                {
                    "particle": truth["particle"].to_numpy()[inside],
                    "focus_x": fit["x"].to_numpy() + corner_x + origin[1],
                    "focus_y": fit["y"].to_numpy() + corner_y + origin[0],
                }
            )
        )
    return pd.concat(parts, ignore_index=True)


def error_table(
    located: pd.DataFrame,
    dataset: Any,
    plane: np.ndarray,
    *,
    truth: str = "focus",
    focus: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """Errors (nm) of localizations of ``dataset``'s particles, one row per spot.

    Parameters
    ----------
    located : DataFrame
        :meth:`Calibration.apply` output with ``particle`` and ``frame`` (the plane).
    dataset : CalibrationDataset
        The sample: ``truth`` and ``z_nm`` (piezo position of each plane).
    plane : ndarray (3,)
        :func:`focal_plane` of the calibration particles.
    truth : {"focus", "geometric"}
        Lateral truth (module notes); ``focus`` needs ``focus`` from :func:`focus_positions`.

    Returns
    -------
    DataFrame
        ``particle``, ``frame``, ``field_x``, ``field_y`` (true, px), ``true_z_nm``,
        ``in_range``, ``err_x_nm``, ``err_y_nm``, ``err_z_nm`` (corrected), ``raw_err_x_nm``,
        ``raw_err_y_nm`` (apparent positions x', y' without correction) and the uncertainties
        that ``apply`` reported, ``x_err_nm``, ``y_err_nm``, ``z_err_nm`` (1σ).
    """
    if truth not in ("focus", "geometric"):
        raise ValueError(f"Expected `truth` to be 'focus' or 'geometric', got {truth!r}.")
    true = dataset.truth.set_index("particle").loc[located["particle"].to_numpy()]
    fx, fy = true["field_x"].to_numpy(), true["field_y"].to_numpy()
    if truth == "focus":
        if focus is None:
            raise ValueError("`truth='focus'` needs `focus` from focus_positions().")
        at = focus.set_index("particle").reindex(located["particle"].to_numpy())
        ref_x, ref_y = at["focus_x"].to_numpy(), at["focus_y"].to_numpy()
    else:
        ref_x, ref_y = fx, fy
    px = dataset.camera.pixel_size_nm
    defocus = true["z_nm"].to_numpy() + np.asarray(dataset.z_nm)[located["frame"].to_numpy()]
    true_z = defocus - (plane[0] + plane[1] * fx + plane[2] * fy)
    return pd.DataFrame(
        {
            "particle": located["particle"].to_numpy(),
            "frame": located["frame"].to_numpy(),
            "field_x": fx,
            "field_y": fy,
            "true_z_nm": true_z,
            "in_range": located["in_range"].to_numpy(bool),
            "err_x_nm": located["x_nm"].to_numpy() - ref_x * px,
            "err_y_nm": located["y_nm"].to_numpy() - ref_y * px,
            "err_z_nm": located["z_nm"].to_numpy() - true_z,
            "raw_err_x_nm": (located["x"].to_numpy() - ref_x) * px,
            "raw_err_y_nm": (located["y"].to_numpy() - ref_y) * px,
            **{f"{a}_err_nm": located[f"{a}_err_nm"].to_numpy() for a in "xyz"},
        }
    )


def rmse(errors: pd.DataFrame, *, z_limit_nm: float | None = None) -> pd.Series:
    """Root-mean-square errors (nm) of the in-range spots, each after one global offset.

    ``z_limit_nm`` keeps only spots with ``|true_z_nm| <= z_limit_nm``. Also returns the
    fraction in range and the count used.
    """
    rows = errors if z_limit_nm is None else errors[np.abs(errors["true_z_nm"]) <= z_limit_nm]
    used = rows[rows["in_range"]]
    out = {}
    for column in ("err_x_nm", "err_y_nm", "err_z_nm", "raw_err_x_nm", "raw_err_y_nm"):
        values = used[column].to_numpy()
        centred = values - values.mean()
        out[column.replace("err_", "rmse_")] = float(np.sqrt(np.mean(centred**2)))
    out["in_range"] = float(rows["in_range"].mean()) if len(rows) else np.nan
    out["n"] = len(used)
    return pd.Series(out)


def error_figure(errors: pd.DataFrame, *, title: str):
    """Apparent and corrected lateral errors, and the z error, against true z (one global
    offset removed per axis, in-range spots)."""
    import matplotlib.pyplot as plt

    used = errors[errors["in_range"]]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, axis in zip(axes[:2], "xy", strict=True):
        for column, label in ((f"raw_err_{axis}_nm", "apparent"), (f"err_{axis}_nm", "corrected")):
            values = used[column] - used[column].mean()
            rms = float(np.sqrt(np.mean(values**2)))
            ax.plot(used["true_z_nm"], values, ".", ms=2, label=f"{label} (RMS {rms:.1f} nm)")
        ax.set(xlabel="true z (nm)", ylabel=f"{axis} error (nm)")
        ax.legend(fontsize=8)
    values = used["err_z_nm"] - used["err_z_nm"].mean()
    axes[2].plot(used["true_z_nm"], values, ".", ms=2)
    axes[2].set(
        xlabel="true z (nm)",
        ylabel="z error (nm)",
        title=f"RMS {float(np.sqrt(np.mean(values**2))):.1f} nm",
    )
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def widefield_study(
    *,
    n_calibration: int = 500,
    n_test: int = 320,
    roi_size: int = 21,
    kinds: tuple[str, ...] = ("zernike", "natural", "nearest"),
    shape: str = "rho_A",
    iterations: int = 0,
    seed: int = 1,
) -> dict[str, Any]:
    """Calibrate a simulated microscope and localize independent particles against truth.

    The calibration: ``n_calibration`` particles of 1 µm (5e5 photons at focus) on a substrate
    tilted by 2 mrad, at 16 stage positions over the 2048² field, through ±3 µm in 50 nm steps,
    with the simulator's default field-dependent aberrations (``seed``). The test sample: another
    ``n_test`` particles (seed + 10) on their own substrate, imaged at 17 piezo positions from
    −2 to +2 µm, localized with :func:`latentz.localization.localize` and
    :meth:`Calibration.apply` (A-normalised shapes use each particle's own reference amplitude,
    as the paper's eq. 6 intends). Each field model in ``kinds`` gets a calibration from the same
    traces.

    Returns
    -------
    dict
        ``calibrations`` and ``errors`` (``{kind: error_table}`` against the ``"focus"`` truth)
        and ``geometric`` (against the ``"geometric"`` truth); ``calibration_dataset``,
        ``test_dataset``, ``spots``, ``plane`` and ``focus``, for :func:`score`.
    """
    from latentz.calibration import calibrate, calibrate_traces
    from latentz.simulate import AberrationMap, calibration_dataset

    aberrations = AberrationMap.default(seed=seed)
    common = {"n_stage_positions": 16, "aberrations": aberrations, "min_spacing_px": 40.0}
    cal_ds = calibration_dataset(
        n_particles=n_calibration, z_nm=np.arange(-3000.0, 3001.0, 50.0), seed=seed, **common
    )
    test_ds = calibration_dataset(
        n_particles=n_test, z_nm=np.linspace(-2000.0, 2000.0, 17), seed=seed + 10, **common
    )
    options = {"camera": cal_ds.camera, "shape": shape, "roi_size": roi_size}
    first = calibrate(
        list(cal_ds.stacks),
        cal_ds.z_nm,
        field_model=kinds[0],
        stage_offsets_px=cal_ds.origins[:, ::-1],
        iterations=iterations,
        **options,
    )
    calibrations = {kinds[0]: first}
    for kind in kinds[1:]:
        calibrations[kind] = calibrate_traces(
            first.traces,
            field_model=kind,
            field_shape=first.options["field_shape"],
            iterations=iterations,
            **options,
        )
    study = {
        "calibrations": calibrations,
        "calibration_dataset": cal_ds,
        "test_dataset": test_ds,
        "spots": localize_dataset(test_ds, roi_size=roi_size),
        "plane": focal_plane(cal_ds.truth),
        "focus": focus_positions(test_ds, roi_size=roi_size),
    }
    scored = {kind: score(cal, study) for kind, cal in calibrations.items()}
    study["errors"] = {kind: pair[0] for kind, pair in scored.items()}
    study["geometric"] = {kind: pair[1] for kind, pair in scored.items()}
    return study


def score(cal: Calibration, study: dict[str, Any]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Localize a :func:`widefield_study`'s test spots with ``cal``; errors against the focus
    and the geometric truths (:func:`error_table`), each with the lateral σ of its own
    convention (``Calibration.apply``'s ``lateral_reference``)."""
    from latentz.calibration.shape import uses_amplitude

    reference = "particle" if uses_amplitude(cal.shape) else "calibration"
    test_ds, plane = study["test_dataset"], study["plane"]
    return tuple(
        error_table(cal.apply(study["spots"], amplitude_reference=reference,
                              lateral_reference=lateral), test_ds, plane, **truth)
        for lateral, truth in (("focus", {"focus": study["focus"]}),
                               ("place", {"truth": "geometric"}))
    )  # fmt: skip

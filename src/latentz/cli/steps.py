"""The file-level pipeline behind the CLI: movies -> localizations -> motion -> report.

Each function composes the array/table stages and adds what a run on real files needs:
provenance, resumable chunking, atomic outputs.
"""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from latentz._shared.provenance import provenance
from latentz._shared.validate import check_choice

if TYPE_CHECKING:
    from latentz.calibration import Calibration
    from latentz.camera import Camera

__all__ = [
    "LOCALIZATION_FORMATS",
    "localize_movies",
    "track_file",
    "motion_outputs",
    "read_used_localizations",
    "report_run",
]


#: Formats ``localize`` writes: latentz's Parquet and CSV, Picasso's HDF5, ThunderSTORM's CSV.
LOCALIZATION_FORMATS = ("parquet", "csv", "picasso", "thunderstorm")


def localize_movies(
    movies: list[str | os.PathLike],
    calibration: str | os.PathLike,
    out: str | os.PathLike,
    *,
    fmt: str | None = None,
    roi_size: int | None = None,
    threshold: float | None = None,
    chunk_frames: int = 200,
    resume: bool = False,
    scheduler: Any = None,
    progress: bool = False,
    camera: dict[str, Any] | None = None,
    track: bool = False,
    device: str = "auto",
) -> pd.DataFrame:
    """Localize movies in 3D with a calibration file and write one table with provenance.

    The movies are read lazily and processed ``chunk_frames`` at a time (memory is bounded by
    the chunk, not the movie); an interrupted run resumes with ``resume=True``. Frames are
    numbered consecutively across movies, and a ``movie`` column names the source.

    ``camera`` overrides the calibration's camera for reading the movies (``camera_file``,
    ``offset``, ``gain``, ``readnoise``, ``pixel_size_nm``, as
    :func:`latentz.cli.options.camera_from_options`), e.g. when they were recorded with another
    gain. Positions are converted to nm with the calibration's pixel size, which its models were
    made in; a different ``pixel_size_nm`` is warned about. ``track`` runs
    :func:`latentz.localize`'s tracking mode within each chunk. ``device`` ("auto", "cpu",
    "cuda") is where detection and fits run (:func:`latentz._shared.engine.resolve_device`).
    """
    from latentz._shared.engine import resolve_device
    from latentz._shared.sanity import check_pixel_size, check_widths
    from latentz.calibration import Calibration
    from latentz.cli.chunked import run_chunked
    from latentz.cli.options import camera_from_options
    from latentz.localization import check_camera_offset, check_roi_fits
    from latentz.localization.mismatch import check_calibration_fits

    if fmt is not None:
        check_choice("fmt", fmt, LOCALIZATION_FORMATS)
    device = resolve_device(device)
    target = Path(out)
    if fmt is None and target.suffix.lower() == ".hdf5":
        fmt = "picasso"
    cal = Calibration.load(calibration)
    overrides = {"camera_file": None, **(camera or {})}
    movie_camera = camera_from_options(**overrides, base=cal.camera)
    check_pixel_size(movie_camera.pixel_size_nm, cal.camera.pixel_size_nm)
    if roi_size is None:  # the fitted widths, hence the shape value, depend on the ROI
        roi_size = cal.roi_size
    frames, bounds = _read_movies(movies)
    check_roi_fits(roi_size, frames.shape[1:], cal)
    options = {
        "roi_size": roi_size,
        "threshold": threshold,
        "chunk_frames": chunk_frames,
        "camera": movie_camera.as_dict(),
        "track": track,
    }
    meta = provenance({"movies": movies, "calibration": calibration}, options)
    # the physical sanity checks speak once for the run, not once per chunk
    check_camera_offset(movie_camera, frames)
    process = functools.partial(
        _localize_chunk,
        frames,
        cal=cal,
        camera=movie_camera,
        names=[str(m) for m in movies],
        bounds=bounds,
        roi_size=roi_size,
        threshold=threshold,
        scheduler=scheduler,
        track=track,
        device=device,
    )
    converted = fmt in ("picasso", "thunderstorm")
    table_path = target if not converted else target.with_name(target.stem + ".latentz.parquet")
    table = run_chunked(
        frames.shape[0],
        process,
        table_path,
        manifest={"inputs": meta["inputs"], "options": options},
        chunk_frames=chunk_frames,
        resume=resume,
        metadata=meta,
        progress=progress,
        finish=functools.partial(check_calibration_fits, calibration=cal),
    )
    check_widths(table[["wx", "wy"]].to_numpy(dtype=np.float64), cal.width_range_px)
    if fmt == "thunderstorm":
        from latentz.io.thunderstorm import write_thunderstorm

        table_path.unlink()
        write_thunderstorm(table, target, pixel_size_nm=cal.camera.pixel_size_nm)
    if fmt == "picasso":
        _to_picasso(table, table_path, target, frames.shape, cal.camera.pixel_size_nm, meta)
    return table


def _read_movies(movies: list[str | os.PathLike]) -> tuple[Any, np.ndarray]:
    """The movies as one lazy (n_frames, H, W) array, and the frame each one ends before."""
    import dask.array as da

    from latentz.io import read_stack

    stacks = [read_stack(m) for m in movies]
    if len({s.shape[1:] for s in stacks}) != 1:
        raise ValueError("Every movie must have the same frame size.")
    frames = da.concatenate(stacks, axis=0) if len(stacks) > 1 else stacks[0]
    return frames, pd.Series([s.shape[0] for s in stacks]).cumsum().to_numpy()


def _localize_chunk(
    frames: Any,
    start: int,
    stop: int,
    *,
    cal: Calibration,
    camera: Camera,
    names: list[str],
    bounds: np.ndarray,
    roi_size: int,
    threshold: float | None,
    scheduler: Any,
    track: bool,
    device: str,
) -> pd.DataFrame:
    """Frames ``start:stop`` localized, corrected by ``cal`` and assessed, with the name of the
    movie each spot comes from; the per-chunk sanity warnings are silenced (said per run)."""
    from latentz._shared.sanity import LatentzWarning
    from latentz.localization import localize
    from latentz.localization.quality import assess

    # read the chunk here (the file is open in this process), fit it where `scheduler` says
    block = np.asarray(frames[start:stop].compute(scheduler="threads"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LatentzWarning)
        spots = localize(
            block,
            camera=camera,
            roi_size=roi_size,
            threshold=threshold,
            method=cal.method,
            scheduler=scheduler,
            track=track,
            device=device,
        )
        spots["frame"] = spots["frame"] + start
        located = assess(cal.apply(spots), cal)
    movie = [names[i] for i in bounds.searchsorted(located["frame"], side="right")]
    located.insert(1, "movie", movie)
    return located


def _to_picasso(
    table: pd.DataFrame,
    table_path: Path,
    target: Path,
    shape: tuple[int, ...],
    pixel_size_nm: float,
    meta: dict[str, Any],
) -> None:
    """Write ``table`` as a Picasso file ``target`` for movies of ``shape`` (n_frames, H, W),
    in place of the chunked table at ``table_path``."""
    from latentz.io.picasso import write_picasso

    table_path.unlink()
    write_picasso(
        table,
        target,
        width=shape[2],
        height=shape[1],
        n_frames=shape[0],
        pixel_size_nm=pixel_size_nm,
        info={"latentz": meta},
    )


def motion_outputs(out: str | os.PathLike) -> dict[str, Path]:
    """The files ``track`` writes for a motion table ``out``: tracks, uncertainty, Table 1."""
    target = Path(out)
    stem = target.with_suffix("")
    return {
        "motion": target,
        "tracks": stem.with_name(stem.name + ".tracks.parquet"),
        "uncertainty": stem.with_name(stem.name + ".uncertainty.csv"),
        "table1": stem.with_name(stem.name + ".table1.csv"),
    }


def track_tables(
    locs: pd.DataFrame,
    *,
    search_range_nm: float = 5000.0,
    memory: int = 3,
    n_sim: int = 10000,
    seed: int = 0,
    static_frames: list[int] | None = None,
    static_locs: pd.DataFrame | None = None,
    good_only: bool = True,
) -> dict[str, pd.DataFrame]:
    """Link the in-range localizations (only the ``good`` ones unless ``good_only`` is False,
    see :mod:`latentz.localization.quality`), fit rigid motion, its Monte Carlo uncertainty and
    Table 1,
    with the drift column (Supp. Note 2: the RMS apparent translation of the constellation per
    frame without intentional motion) from ``static_frames`` of ``locs`` or from
    ``static_locs``, a localization table recorded without intentional motion. The motion
    table's ``attrs["quality"]`` says how many in-range rows were dropped, and why."""
    from latentz._shared.validate import check_columns
    from latentz.localization.quality import good_rows
    from latentz.motion import (
        drift,
        link,
        motion_uncertainty,
        resolve_by_icp,
        rigid_motion,
        table1,
    )

    check_columns("locs", locs, ("frame", "x_nm", "y_nm", "z_nm", "in_range"))
    if static_frames and static_locs is not None:
        raise ValueError(
            "Give the drift's static data as `static_frames` or `static_locs`, not both."
        )
    if static_locs is not None:
        check_columns("static_locs", static_locs, ("frame", "x_nm", "y_nm", "z_nm", "in_range"))
        still = static_locs[static_locs["in_range"].astype(bool)]
        if good_only:
            still, _ = good_rows(still)
        if still["frame"].nunique() < 2:
            raise ValueError("The static localizations must span at least two frames in range.")
    kept, used = locs[locs["in_range"].astype(bool)], ""
    if good_only:
        kept, used = good_rows(kept)
    if kept["frame"].nunique() < 2:
        raise ValueError("Tracking needs in-range localizations in at least two frames.")
    moving = kept if not static_frames else kept[~kept["frame"].isin(static_frames)]
    tracks = link(moving, search_range_nm=search_range_nm, memory=memory, predict=True)
    # where linking leaves a cycle ambiguous, ICP registers the two frames directly
    motion = resolve_by_icp(rigid_motion(tracks), moving, max_distance_nm=search_range_nm)
    motion.attrs["quality"] = used
    uncertainty = motion_uncertainty(tracks, motion, n_sim=n_sim, seed=seed)
    drift_nm = None
    if static_frames:
        still = kept[kept["frame"].isin(static_frames)]
    if static_frames or static_locs is not None:
        drift_nm = drift(link(still, search_range_nm=search_range_nm, memory=memory))
    summary = table1(motion, uncertainty, drift_nm=drift_nm)
    return {"tracks": tracks, "motion": motion, "uncertainty": uncertainty, "table1": summary}


def _static_locs(
    static: str | os.PathLike, calibration: str | os.PathLike | None, folder: Path
) -> pd.DataFrame:
    """The localizations of a static recording: a table as it is, a movie localized with the
    calibration (into ``folder``)."""
    from latentz.io import TABLE_FORMATS, read_table

    if Path(static).suffix.lower().lstrip(".") in (*TABLE_FORMATS, "pq"):
        return read_table(static)[0]
    if calibration is None:
        raise ValueError(
            f"--static {Path(static).name} is a movie: pass --calibration to localize it, "
            "or give a localization table."
        )
    return localize_movies([static], calibration, folder / "static.parquet")


def track_file(
    locs_path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    static: str | os.PathLike | None = None,
    calibration: str | os.PathLike | None = None,
    **options: Any,
) -> pd.DataFrame:
    """:func:`track_tables` on a localization file; writes the motion table and its siblings
    (:func:`motion_outputs`) with provenance; returns the motion table.

    ``static`` is a recording without intentional motion for Table 1's drift column: a
    localization table, or a movie that ``calibration`` localizes."""
    import tempfile

    from latentz.io import read_localizations, write_table

    inputs = {"localizations": locs_path}
    for role, path in (("static", static), ("calibration", calibration)):
        if path is not None:
            if not Path(path).exists():
                raise FileNotFoundError(f"No such {role} file: {path}")
            inputs[role] = path
    locs, _ = read_localizations(locs_path)
    if static is not None:
        with tempfile.TemporaryDirectory() as folder:
            options["static_locs"] = _static_locs(static, calibration, Path(folder))
    tables = track_tables(locs, **options)
    options.pop("static_locs", None)
    meta = provenance(inputs, options)
    meta["centre_of_rotation_nm"] = list(tables["motion"].attrs.get("centre_nm", []))
    paths = motion_outputs(out)
    write_table(tables["tracks"], paths["tracks"], metadata=meta)
    write_table(tables["uncertainty"].reset_index(names="dof"), paths["uncertainty"])
    write_table(tables["table1"].reset_index(names="dof"), paths["table1"])
    write_table(tables["motion"], paths["motion"], metadata=meta)
    return tables["motion"]


def read_used_localizations(
    path: str | os.PathLike, pixel_size_nm: float | None = None, *, good_only: bool = True
) -> tuple[pd.DataFrame, str]:
    """A localization file in any format (:func:`latentz.io.read_localizations`), its in-range
    rows (all rows of 2D data, where none has a z), only the good ones unless ``good_only`` is
    False, and what was dropped, in words."""
    from latentz.io import read_localizations
    from latentz.localization.quality import good_rows

    table, _ = read_localizations(path, pixel_size_nm=pixel_size_nm)
    if "in_range" in table and table["in_range"].any():
        table = table[table["in_range"].astype(bool)]
    said = ""
    if good_only:
        table, said = good_rows(table)
    if table.empty:
        raise ValueError(f"{Path(path).name} holds no in-range localizations to use.")
    return table, said


def report_run(run_dir: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write one HTML report of whatever a run folder holds: calibration (``*.h5``),
    localization tables (``*.parquet``) and motion tables (with their ``track`` siblings)."""
    from latentz.calibration import Calibration
    from latentz.io import read_table
    from latentz.report import sections, write_report

    folder = Path(run_dir).resolve()
    quality, parts = [], []
    for path in sorted(folder.glob("*.h5")):
        cal = Calibration.load(path)
        quality.append(sections.quality_section(cal, name=path.name))
        parts.append(sections.calibration_section(cal, name=path.name))
        widefield = sections.widefield_section(cal, name=path.name)
        if widefield is not None:
            parts.append(widefield)
    for path in sorted(folder.glob("*.parquet")):
        if path.name.endswith(".tracks.parquet"):
            continue
        table, _ = read_table(path)
        if {"z_nm", "in_range", "x_err_nm"} <= set(table.columns):
            parts.append(sections.localization_section(table, name=path.name))
    for path in sorted(folder.glob("*.tracks.parquet")):
        paths = motion_outputs(path.with_name(path.name.replace(".tracks.parquet", ".csv")))
        if not all(p.exists() for p in paths.values()):
            continue
        tracks = read_table(paths["tracks"])[0]
        motion, meta = read_table(paths["motion"])
        if (meta or {}).get("centre_of_rotation_nm"):
            motion.attrs["centre_nm"] = meta["centre_of_rotation_nm"]
        unc = read_table(paths["uncertainty"])[0].set_index("dof")
        summary = read_table(paths["table1"])[0].set_index("dof")
        name = paths["motion"].name
        parts.append(sections.motion_section(tracks, motion, unc, summary, name=name))
    if not parts:
        raise ValueError(f"{folder} holds no calibration, localization or motion files.")
    return write_report(
        quality + parts,
        out,
        title=f"latentz report: {folder.name}",
        png_dir=Path(out).with_suffix("").with_name(Path(out).stem + "-figures"),
    )

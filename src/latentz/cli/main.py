"""The ``latentz`` command line.

Every command ends bad input with one clear line on stderr and a non-zero exit status, never a
traceback, and writes its outputs atomically.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import click

from latentz import __version__
from latentz.camera import Camera

EXIT_BAD_INPUT = 2
EXIT_INTERNAL = 1
EXIT_INTERRUPTED = 130


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _warning_line(message, category, *args, **kwargs) -> str:
    """A warning as one ``latentz: warning: ...`` line, without file paths or source lines
    (Python's warnings.formatwarning, so recorders such as pytest.warns still see the warning):
    latentz's own (LatentzWarning) as they are, others with their category."""
    from latentz._shared.sanity import LatentzWarning

    kind = "" if issubclass(category, LatentzWarning) else f"{category.__name__}: "
    return f"latentz: warning: {kind}{_first_line(message)}\n"


class _Group(click.Group):
    """A click group that turns expected errors into one line on stderr."""

    def invoke(self, ctx: click.Context):
        try:
            formatwarning, warnings.formatwarning = warnings.formatwarning, _warning_line
            try:
                return super().invoke(ctx)
            finally:
                warnings.formatwarning = formatwarning
        except (click.exceptions.Exit, click.ClickException):
            raise
        except (KeyboardInterrupt, click.exceptions.Abort):
            resumable = ctx.invoked_subcommand == "localize"
            click.echo(
                "latentz: interrupted"
                + (
                    "; the finished chunks are kept: run the same command with --resume to carry on"
                    if resumable
                    else "; nothing was written"
                ),
                err=True,
            )
            sys.exit(EXIT_INTERRUPTED)
        except (ValueError, TypeError, FileNotFoundError, OSError, KeyError) as exc:
            click.echo(f"latentz: error: {_first_line(exc)}", err=True)
            sys.exit(EXIT_BAD_INPUT)
        except Exception as exc:  # noqa: BLE001 - a bug: one line, the traceback on request
            if os.environ.get("LATENTZ_DEBUG"):
                raise
            click.echo(
                f"latentz: internal error ({type(exc).__name__}: {_first_line(exc)}); "
                "rerun with LATENTZ_DEBUG=1 for the traceback and please report it",
                err=True,
            )
            sys.exit(EXIT_INTERNAL)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="latentz")
def main() -> None:
    """latentz: accurate 3D localization microscopy by intrinsic aberration calibration."""


@main.command()
@click.argument("kind", type=click.Choice(["calibration", "gear", "apertures"]))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for the TIFF stacks, ground-truth CSV and metadata JSON.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--quick", is_flag=True, help="A small dataset, for a fast look.")
@click.option("--plot", is_flag=True, help="Also write the PSF gallery PNG.")
def simulate(kind: str, out_dir: Path, seed: int, quick: bool, plot: bool) -> None:
    """Simulate a dataset with ground truth: calibration stacks, a gear movie or apertures."""
    from latentz._shared.preflight import check_output_folder

    check_output_folder(out_dir)
    from latentz.simulate import write_dataset

    written = write_dataset(kind, out_dir, seed=seed, quick=quick, plot=plot)
    for path in written:
        click.echo(str(path))


def _quiet_option(func):
    return click.option("--quiet", is_flag=True, help="No progress bars.")(func)


def _camera_options(func):
    options = [
        click.option(
            "--camera",
            "camera_file",
            type=click.Path(dir_okay=False),
            help="Camera JSON: offset, gain, readnoise, pixel_size_nm[, flatfield].",
        ),
        click.option(
            "--offset",
            type=float,
            help="Camera offset, ADU. [calibrate default: the image minimum; localize: the "
            "calibration's]",
        ),
        click.option(
            "--gain",
            type=float,
            help="Camera gain, photoelectrons per ADU. [calibrate default: from the stack's "
            "photon-transfer curve; localize: the calibration's]",
        ),
        click.option(
            "--readnoise",
            type=float,
            help=f"Read noise, photoelectrons. [default: {Camera().readnoise:g}; localize: the "
            "calibration's]",
        ),
        click.option(
            "--pixel-size-nm",
            type=float,
            help="Pixel size in the sample, nm. [calibrate default: the file's metadata (OME, "
            f"ImageJ, MicroManager), else {Camera().pixel_size_nm:g}; localize: the "
            "calibration's]",
        ),
        click.option(
            "--emccd",
            is_flag=True,
            help="An EMCCD with EM gain on: its excess noise doubles each pixel's variance, so "
            "the --gain (photoelectrons per ADU: electrons per ADU over the EM gain) and "
            "--readnoise (over the EM gain) given here or in --camera are halved to "
            "Poisson-equivalent counts, in which photons are then reported. A gain estimated "
            "from the photon-transfer curve needs no halving.",
        ),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _device_option(func):
    return click.option(
        "--device",
        default="auto",
        show_default=True,
        type=click.Choice(["auto", "cpu", "cuda"]),
        callback=_resolve_device,
        help="Fit (and detect) on the CPU or an NVIDIA GPU (needs `pip install 'latentz[gpu]'`).",
    )(func)


def _resolve_device(ctx: click.Context, param: click.Parameter, device: str) -> str:
    """The device, resolved while the options are read: before any file is opened."""
    from latentz._shared.engine import resolve_device

    return resolve_device(device)


def _progress(quiet: bool) -> bool:
    return not quiet and sys.stderr.isatty()


@main.command()
@click.argument("stacks", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--z-start", "z_start_nm", type=float, help="Piezo z of the first plane, nm.")
@click.option("--z-step", "z_step_nm", type=float, help="Piezo step between planes, nm.")
@click.option("--z-file", type=click.Path(dir_okay=False), help="Piezo z of each plane, nm.")
@click.option(
    "--stage-offsets",
    type=click.Path(dir_okay=False),
    help="CSV, one 'x_px,y_px' row per stack: where its pixel [0, 0] lies in the field.",
)
@_camera_options
@click.option(
    "--shape",
    default=None,
    type=click.Choice(["rho", "rho_w", "rho_A", "auto", "auto_A"]),
    help="Shape parameter for z. [default: the one with the best expected sigma_z for "
    "single molecules and for emitters like the calibration particles; the calibration "
    "records why]",
)
@click.option(
    "--roi-size",
    type=int,
    default=None,
    help="ROI side, pixels (odd). [default: the candidate with the best cross-validated z error]",
)
@click.option(
    "--field-model",
    default="auto",
    show_default=True,
    type=click.Choice(["auto", "zernike", "natural", "curves", "nearest"]),
)
@click.option("--n-terms", default=400, show_default=True, help="Zernike terms.")
@click.option(
    "--particle-nm",
    "particle_diameter_nm",
    type=float,
    default=None,
    help="Diameter of the calibration beads, nm: calibrate for point emitters (single "
    "molecules) by taking the beads' blur off their images. [default: none, the calibration "
    "holds the beads' own shapes]",
)
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Calibration file to write (HDF5).",
)
@_device_option
@_quiet_option
def calibrate(
    stacks,
    z_start_nm,
    z_step_nm,
    z_file,
    stage_offsets,
    camera_file,
    offset,
    gain,
    readnoise,
    pixel_size_nm,
    emccd,
    shape,
    roi_size,
    field_model,
    n_terms,
    particle_diameter_nm,
    out,
    device,
    quiet,
) -> None:
    """Calibrate from through-focus stacks (one per stage position)."""
    from latentz._shared.engine import resolve_device
    from latentz._shared.preflight import check_output_file
    from latentz._shared.provenance import provenance
    from latentz.calibration import calibrate as run_calibration
    from latentz.camera.source import camera_for_stacks
    from latentz.cli.options import (
        camera_from_options,
        read_camera_file,
        stage_offsets_px,
        z_positions,
    )
    from latentz.io import read_stack

    check_output_file(out, (".h5", ".hdf5"))
    device = resolve_device(device)

    given = {"offset": offset, "gain": gain, "readnoise": readnoise, "pixel_size_nm": pixel_size_nm}
    flatfield = None
    if camera_file is not None:
        from_file, flatfield = read_camera_file(camera_file)
        given = {**from_file, **{k: v for k, v in given.items() if v is not None}}
    for name, value in given.items():  # bad values fail here, before any reading
        if value is not None:
            camera_from_options(None, **{name: value})
    loaded = [read_stack(path) for path in stacks]
    for path, stack in zip(stacks, loaded, strict=True):
        if stack.shape[0] == 1:
            raise ValueError(
                f"{Path(path).name} holds a single image, not a through-focus stack: "
                "calibration needs one image per z plane."
            )
    if len({s.shape[0] for s in loaded}) != 1:
        raise ValueError("Every calibration stack must have the same number of planes.")
    z = z_positions(loaded[0].shape[0], z_start_nm=z_start_nm, z_step_nm=z_step_nm, z_file=z_file)
    offsets = None if stage_offsets is None else stage_offsets_px(stage_offsets, len(loaded))
    arrays = [s.compute() for s in loaded]
    camera, said = camera_for_stacks(arrays, stacks[0], given, flatfield=flatfield, emccd=emccd)
    cal = run_calibration(
        arrays,
        z,
        camera=camera,
        shape=shape,
        roi_size=roi_size,
        field_model=field_model,
        n_terms=n_terms,
        progress=_progress(quiet),
        stage_offsets_px=offsets,
        sources=[str(p) for p in stacks],
        device=device,
        particle_diameter_nm=particle_diameter_nm,
    )
    inputs = {"stacks": list(stacks)}
    for role, path in (
        ("z_file", z_file),
        ("camera", camera_file),
        ("stage_offsets", stage_offsets),
    ):
        if path is not None:
            inputs[role] = path
    cal.save(out, provenance=provenance(inputs, {"command": "latentz calibrate"}))
    click.echo(
        f"{out}: {len(cal.kept)} of {len(cal.culled)} particles kept, tilt {cal.tilt_mrad:.2f} "
        f"mrad, ROI {cal.roi_size} px, field model {cal.field_model}"
    )
    click.echo(said)
    click.echo(cal.shape_choice["reason"] if cal.shape_choice else f"shape={cal.shape!r}, as given")


@main.command()
@click.argument("movies", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option(
    "--calibration",
    "cal_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="Calibration file from `latentz calibrate`.",
)
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Localization table (.parquet, .csv, .hdf5 with --format picasso, .csv with --format "
    "thunderstorm).",
)
@click.option(
    "--format",
    "fmt",
    default=None,
    type=click.Choice(["parquet", "csv", "picasso", "thunderstorm"]),
    help="Output format (default from the suffix: .parquet, .csv latentz's, .hdf5 Picasso's).",
)
@click.option(
    "--roi-size", type=int, default=None, help="ROI side, pixels (odd); default: the calibration's."
)
@click.option("--threshold", type=float, help="Detection threshold, background-noise units.")
@click.option("--chunk-frames", default=200, show_default=True, help="Frames per chunk.")
@click.option("--resume", is_flag=True, help="Carry on from the last finished chunk.")
@click.option("--scheduler", default=None, help="dask.distributed scheduler address.")
@click.option(
    "--exposure-ms",
    default=1.0,
    show_default=True,
    type=float,
    help="Exposure of the movies, ms: sets the acquisition rate the speed is compared with.",
)
@click.option(
    "--track",
    is_flag=True,
    help="Tracking mode: fit each emitter where its last positions predict it.",
)
@_camera_options
@_device_option
@_quiet_option
def localize(
    movies,
    cal_path,
    out,
    fmt,
    roi_size,
    threshold,
    chunk_frames,
    resume,
    scheduler,
    exposure_ms,
    track,
    camera_file,
    offset,
    gain,
    readnoise,
    pixel_size_nm,
    emccd,
    device,
    quiet,
) -> None:
    """Localize every emitter in 3D with a calibration.

    The movies are read with the calibration's camera; camera options override its values (for
    movies recorded with another gain or offset). The achieved frames/s is reported against the
    global-shutter acquisition rate for the movies' rows at --exposure-ms.
    """
    import time

    from latentz._shared.preflight import check_output_file
    from latentz.camera.readout import frame_rate_hz
    from latentz.cli.steps import localize_movies
    from latentz.io import read_stack
    from latentz.localization.quality import reasons, summary

    check_output_file(out, (".parquet", ".pq", ".csv", ".hdf5"))
    if exposure_ms <= 0:
        raise ValueError(f"--exposure-ms must be > 0, got {exposure_ms}.")
    shapes = [read_stack(m).shape for m in movies]
    start = time.perf_counter()
    camera = {
        "camera_file": camera_file,
        "offset": offset,
        "gain": gain,
        "readnoise": readnoise,
        "pixel_size_nm": pixel_size_nm,
        "emccd": emccd,
    }

    table = localize_movies(
        movies,
        cal_path,
        out,
        fmt=fmt,
        roi_size=roi_size,
        threshold=threshold,
        chunk_frames=chunk_frames,
        resume=resume,
        scheduler=scheduler,
        progress=_progress(quiet),
        camera=camera,
        track=track,
        device=device,
    )
    counts = summary(table)
    flags = reasons(counts)
    click.echo(
        f"{out}: {counts['rows']} localizations, {int(table['in_range'].sum())} in range, "
        f"{counts['good']} good" + (f" (not good: {flags})" if flags else "")
    )
    achieved_hz = sum(shape[0] for shape in shapes) / (time.perf_counter() - start)
    acquired_hz = frame_rate_hz(exposure_ms, shapes[0][1])
    click.echo(
        f"{achieved_hz:.1f} frames/s, {achieved_hz / acquired_hz:.2f}x the acquisition rate "
        f"({acquired_hz:.1f} Hz: {exposure_ms:g} ms exposure, {shapes[0][1]} rows)"
    )


@main.command()
@click.argument("locs", type=click.Path(dir_okay=False))
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Motion table (.csv or .parquet); uncertainty and Table 1 go beside it.",
)
@click.option(
    "--search-range-nm",
    default=2000.0,
    show_default=True,
    help="Largest displacement of a particle between frames, nm.",
)
@click.option("--memory", default=2, show_default=True, help="Frames a particle may vanish.")
@click.option("--n-sim", default=10000, show_default=True, help="Monte Carlo simulations.")
@click.option("--seed", default=0, show_default=True)
@click.option(
    "--static",
    type=click.Path(dir_okay=False),
    help="Localizations (or a movie, with --calibration) recorded without intentional motion: "
    "fills Table 1's drift column.",
)
@click.option(
    "--calibration",
    "cal_path",
    type=click.Path(dir_okay=False),
    help="Calibration file, to localize a --static movie.",
)
@click.option(
    "--all-rows", is_flag=True, help="Use every in-range localization, not only the good ones."
)
@_quiet_option
def track(
    locs, out, search_range_nm, memory, n_sim, seed, static, cal_path, all_rows, quiet
) -> None:
    """Link localizations and measure rigid motion in six degrees of freedom.

    Only the good localizations are used (see the `good` column and its flags) unless
    --all-rows is given; the command says how many it dropped and why.
    """
    from latentz._shared.preflight import check_output_file
    from latentz.cli.steps import track_file

    check_output_file(out, (".csv", ".parquet", ".pq"))
    motion = track_file(
        locs,
        out,
        static=static,
        calibration=cal_path,
        search_range_nm=search_range_nm,
        memory=memory,
        n_sim=n_sim,
        seed=seed,
        good_only=not all_rows,
    )
    if motion.attrs.get("quality"):
        click.echo(motion.attrs["quality"])
    click.echo(f"{out}: {len(motion)} transitions")


def _locs_argument(func):
    func = click.option(
        "--pixel-size-nm",
        type=float,
        default=None,
        help="Camera pixel size, nm, for a Picasso file without one in its YAML.",
    )(func)
    return click.argument("locs", type=click.Path(dir_okay=False, exists=True))(func)


def _out_file(help_text: str):
    return click.option(
        "--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help=help_text
    )


@main.command()
@_locs_argument
@_out_file(
    "Image: .png (RGB with scale and z colour bars, x-y and x-z views) or .tif (float density "
    "and mean z, pixel size in the metadata)."
)
@click.option("--pixel-nm", default=10.0, show_default=True, help="Image pixel, nm.")
@click.option(
    "--color", default="z", show_default=True, help="Column for the colour ('z', or 'none')."
)
@click.option(
    "--blur",
    default="precision",
    show_default=True,
    help="'precision' (each localization's reported error), a width in nm, or 'none'.",
)
@click.option("--all-rows", is_flag=True, help="Draw every localization, not only the good ones.")
def render(locs, pixel_size_nm, out, pixel_nm, color, blur, all_rows) -> None:
    """Render localizations (latentz, Picasso or ThunderSTORM files) as a super-resolution image."""
    from latentz._shared.preflight import check_output_file
    from latentz.analysis import RENDER_SUFFIXES, write_render
    from latentz.cli.steps import read_used_localizations

    check_output_file(out, RENDER_SUFFIXES)
    width = None if blur == "none" else (blur if blur == "precision" else _number(blur, "--blur"))
    table, said = read_used_localizations(locs, pixel_size_nm, good_only=not all_rows)
    write_render(
        table, out, pixel_nm=pixel_nm, color=None if color == "none" else color, blur=width
    )
    click.echo(f"{out}: {len(table)} localizations drawn" + (f" ({said})" if said else ""))


def _number(text: str, option: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(
            f"{option} takes 'precision', a number of nm or 'none', got {text!r}."
        ) from None


@main.command()
@_locs_argument
@_out_file("Corrected table (.parquet or .csv); the drift figure goes beside it (.drift.png).")
@click.option("--method", default="rcc", show_default=True, type=click.Choice(["rcc", "fiducials"]))
@click.option("--segment-frames", default=1000, show_default=True, help="RCC: frames per segment.")
@click.option("--pixel-nm", default=20.0, show_default=True, help="RCC: image pixel, nm.")
@click.option(
    "--fiducial-radius-nm",
    default=300.0,
    show_default=True,
    help="Fiducials: how far a fiducial may wander (drift included), nm.",
)
def drift(locs, pixel_size_nm, out, method, segment_frames, pixel_nm, fiducial_radius_nm) -> None:
    """Correct drift in x, y, z by RCC or fiducials; the drift removed is kept as columns."""
    from latentz._shared.figures import save_figure
    from latentz._shared.preflight import check_output_file
    from latentz._shared.provenance import provenance
    from latentz.analysis import correct_drift, drift_figure
    from latentz.io import read_localizations, write_table

    check_output_file(out, (".parquet", ".pq", ".csv"))
    table, _ = read_localizations(locs, pixel_size_nm=pixel_size_nm)
    options = {
        "method": method,
        "segment_frames": segment_frames,
        "pixel_nm": pixel_nm,
        "fiducial_radius_nm": fiducial_radius_nm,
    }
    corrected = correct_drift(table, **options)
    figure = out.with_name(out.with_suffix("").name + ".drift.png")
    write_table(corrected, out, metadata=provenance({"localizations": locs}, options))
    save_figure(drift_figure(corrected), figure)
    removed = corrected.groupby("frame")[["drift_x_nm", "drift_y_nm", "drift_z_nm"]].first()
    span = removed.max() - removed.min()
    click.echo(
        f"{out}: drift removed spans {span.iloc[0]:.1f}, {span.iloc[1]:.1f}, {span.iloc[2]:.1f} "
        f"nm in x, y, z ({corrected.attrs['drift']}); figure {figure}"
    )


@main.command()
@_locs_argument
@click.option("--pixel-nm", default=5.0, show_default=True, help="Image pixel, nm.")
@click.option(
    "--split",
    default="blocks",
    show_default=True,
    type=click.Choice(["blocks", "random", "odd_even"]),
    help="How the data are halved: 20 blocks of frames, each localization, or frame parity.",
)
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), help="Figure of the curve (.png)."
)
@click.option("--all-rows", is_flag=True, help="Use every localization, not only the good ones.")
def frc(locs, pixel_size_nm, pixel_nm, split, out, all_rows) -> None:
    """Resolution by Fourier ring correlation (1/7 threshold) of two halves of the data."""
    from latentz._shared.figures import save_figure
    from latentz._shared.preflight import check_output_file
    from latentz.analysis import frc as ring_correlation
    from latentz.cli.steps import read_used_localizations

    if out is not None:
        check_output_file(out, (".png",))
    table, said = read_used_localizations(locs, pixel_size_nm, good_only=not all_rows)
    result = ring_correlation(table, pixel_nm=pixel_nm, split=split)
    if out is not None:
        save_figure(result.figure(), out)
    click.echo(
        f"FRC resolution {result.resolution_nm:.1f} nm ({split} halves, {pixel_nm:g} nm pixels, "
        f"{len(table)} localizations)" + (f"; {said}" if said else "")
    )


@main.command()
@click.argument("run_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path))
def report(run_dir: Path, out: Path) -> None:
    """Write one self-contained HTML report of a run folder."""
    from latentz._shared.preflight import check_output_file
    from latentz.cli.steps import report_run

    check_output_file(out, (".html", ".htm"))
    click.echo(str(report_run(run_dir, out)))


@main.command()
@click.option(
    "--out",
    "out_dir",
    default="demo-run",
    show_default=True,
    type=click.Path(file_okay=False, path_type=Path),
)
@click.option("--quick", is_flag=True, help="A small run (under a minute).")
@click.option("--seed", default=0, show_default=True)
@_quiet_option
def demo(out_dir: Path, quick: bool, seed: int, quiet: bool) -> None:
    """Simulate, calibrate, localize, track and report: the whole job on built-in data."""
    from latentz.cli.demo import run_demo

    summary = run_demo(out_dir, quick=quick, seed=seed, progress=_progress(quiet))
    for line in summary:
        click.echo(line)

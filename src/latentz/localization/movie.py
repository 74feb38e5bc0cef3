"""Localize emitters in movies: detection and eq. 1 fits, chunk by chunk over frames.

The movie (numpy, dask, or an image file opened lazily) is cut into chunks of frames. Each chunk is
one task that reads its frames, converts them to photoelectrons, detects emitters and fits them
(:mod:`latentz.detect`, :mod:`latentz.fit`), and returns a table. By default, on the CPU, the
chunks run in this process, the next one detected while this one is fitted; given a scheduler,
tasks run on it in waves of a few chunks. Either way only a few chunks are in memory at once and
a movie larger than memory works; the same code runs on a dask.distributed cluster.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from typing import TYPE_CHECKING, Any

import dask
import dask.array as da
import numba
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from latentz._shared.engine import resolve_device
from latentz._shared.medians import row_medians
from latentz._shared.sanity import check_offset
from latentz._shared.threads import concurrent_kernels_safe
from latentz._shared.validate import check_choice, check_int
from latentz.camera import Camera
from latentz.detect import Detections, cut_photons, detect_arrays
from latentz.fit.api import FIT_COLUMNS, METHODS, result_table
from latentz.io import as_frames, open_movie, read_frames
from latentz.localization.crowding import with_crowding_errors
from latentz.localization.edges import with_truncation_errors
from latentz.localization.follow import localize_tracked
from latentz.localization.mismatch import check_calibration_fits
from latentz.localization.neighbours import refit_without_neighbours
from latentz.localization.pairs import PAIR_COLUMNS, split_pairs
from latentz.localization.quality import assess
from latentz.localization.recentre import fit_recentred, on_calibration_pixels

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration

__all__ = ["localize", "check_camera_offset", "check_roi_fits", "LOCALIZE_COLUMNS"]

#: Columns of one chunk's detections and fits, in order.
_CHUNK_COLUMNS = ("frame", *FIT_COLUMNS, "snr", "edge", "close_pair", *PAIR_COLUMNS)
#: Columns of the table returned by `localize` without a calibration, in order.
LOCALIZE_COLUMNS = (*_CHUNK_COLUMNS, "duplicate", "unresolved", "good")
_LOCAL_SCHEDULERS = ("threads", "processes", "synchronous")
_CHUNK_BYTES = 64 * 2**20


def check_camera_offset(camera: Camera, movie: Any) -> None:
    """Warn if the camera offset (ADU) is above the median of the movie's first frame (every
    fourth pixel): an offset above most pixels means the wrong camera settings.

    A lazy movie is read here, in this process: through a dask.distributed client its file
    reader would have to be pickled, and it holds a lock."""
    sample = movie[0][::4, ::4]
    if isinstance(sample, da.Array):
        sample = sample.compute(scheduler="synchronous")
    check_offset(camera.offset, float(row_medians(np.asarray(sample).reshape(1, -1))[0]))


def check_roi_fits(
    roi_size: int, frame_shape: tuple[int, ...], calibration: Calibration | None = None
) -> None:
    """Raise one line when ``roi_size`` (pixels) is even or larger than the frames; when it is
    the calibration's, the line names both sizes and the two ways out."""
    largest = min(frame_shape)
    if roi_size % 2 == 1 and roi_size <= largest:
        return
    fits = largest if largest % 2 else largest - 1
    if calibration is not None and roi_size == calibration.roi_size and roi_size > largest:
        raise ValueError(
            f"The calibration's {roi_size} px ROI does not fit the {frame_shape[0]} x "
            f"{frame_shape[1]} px images: recalibrate with roi_size={fits} (--roi-size {fits}; "
            f"any odd size up to {fits} fits), or localize with roi_size={fits} and accept the "
            "warning that z is then measured in another ROI than the calibration's."
        )
    raise ValueError(f"Expected `roi_size` to be odd and at most {largest}, got {roi_size}.")


def _localize_chunk(
    block: np.ndarray,
    first_frame: int,
    camera: Camera | None,
    roi_size: int,
    threshold: float | None,
    method: str,
    sigma: float,
    device: str = "cpu",
    calibration: Calibration | None = None,
    pairs: bool = False,
) -> pd.DataFrame:
    """Detect and fit the frames of one chunk on ``device`` ("cpu" or "cuda"): `_detect_chunk`,
    then `_fit_chunk`."""
    block = np.asarray(block)  # as stored: both devices convert to photoelectrons themselves
    found = _detect_chunk(block, camera, roi_size, threshold, sigma, device)
    return _fit_chunk(block, found, first_frame, camera, roi_size, method, device, calibration,
                      pairs)  # fmt: skip


def _detect_chunk(
    block: np.ndarray,
    camera: Camera | None,
    roi_size: int,
    threshold: float | None,
    sigma: float,
    device: str,
) -> Detections:
    """The emitters of one chunk's frames ``block`` (as stored), detected on ``device``."""
    if device == "cuda":
        from latentz.detect._cuda import detect_arrays_cuda as detect_on_device
    else:
        detect_on_device = detect_arrays
    return detect_on_device(
        block, roi_size=roi_size, threshold=threshold, sigma=sigma, camera=camera
    )


def _fit_chunk(
    block: np.ndarray,
    found: Detections,
    first_frame: int,
    camera: Camera | None,
    roi_size: int,
    method: str,
    device: str,
    calibration: Calibration | None,
    pairs: bool,
) -> pd.DataFrame:
    """Fit the emitters ``found`` in one chunk's frames ``block`` on ``device``; ``x, y`` in
    full-frame pixels, ``frame`` counted from ``first_frame``. With a ``calibration``, spots it
    reads far from focus are fitted again in its ROI convention
    (:func:`~latentz.localization.recentre.on_calibration_pixels`). With ``pairs``, close pairs
    are fitted as two emitters (:mod:`latentz.localization.pairs`, what one emitter looks like
    from ``calibration``)."""
    if len(found.frame) == 0:
        return pd.DataFrame({c: pd.Series(dtype=_dtype(c)) for c in _CHUNK_COLUMNS})
    readnoise = camera.readnoise if camera is not None else 0.0

    def read(moved: np.ndarray, row0: np.ndarray, col0: np.ndarray) -> np.ndarray:
        return cut_photons(block, found.frame[moved], row0, col0, roi_size, camera)

    done = fit_recentred(
        read, found.rois, (found.row0, found.col0), (found.row, found.col),
        frame_shape=block.shape[-2:], method=method, readnoise=readnoise, device=device,
    )  # fmt: skip
    if calibration is not None:
        done = on_calibration_pixels(done, read, calibration, frame_shape=block.shape[-2:],
                                     method=method, readnoise=readnoise, device=device)  # fmt: skip
    fit = refit_without_neighbours(
        done.fit, done.rois, np.column_stack([done.col0, done.row0]), found.frame, done.windows,
        method=method, readnoise=readnoise, device=device,
    )  # fmt: skip
    table = result_table(
        fit, frame=first_frame + found.frame, snr=found.snr, edge=done.edge,
        close_pair=found.close_pair,
    )  # fmt: skip
    if not pairs:
        return table.assign(pair=-1, merged=False)
    table.attrs["roi_size"] = roi_size
    return split_pairs(table, done.rois, np.column_stack([done.col0, done.row0]),
                       readnoise=readnoise, calibration=calibration)  # fmt: skip


def _chunk_with(options: tuple, block: np.ndarray, first_frame: int) -> pd.DataFrame:
    """`_localize_chunk` of ``block`` with the movie's ``options`` (its arguments after
    ``first_frame``)."""
    return _localize_chunk(block, first_frame, *options)


def _source(frames: Any, movie: Any, start: int, stop: int) -> Any:
    """What a task reads: for a file, its path and frame range (workers open the file
    themselves, so nothing unpicklable enters the task graph); otherwise the frames' slice."""
    if isinstance(frames, str | os.PathLike):
        return dask.delayed(read_frames)(os.fspath(frames), start, stop)
    return movie[start:stop]


def _dtype(column: str) -> str:
    if column in ("converged", "edge", "close_pair", "merged", "duplicate", "unresolved", "good"):
        return "bool"
    return "int64" if column in ("frame", "iterations", "pair") else "float64"


def _scheduler_and_width(scheduler: Any, device: str) -> tuple[Any, int, Any]:
    """(scheduler for dask.compute, chunks per wave, client to close when done)."""
    cores = os.cpu_count() or 1
    if scheduler in (None, "threads") and not concurrent_kernels_safe():
        # chunks in threads would launch parallel kernels at once, which numba's workqueue
        # threading layer answers by aborting the process
        return "synchronous", 1, None
    if scheduler is None:  # on the GPU (`_overlapped` runs the CPU's chunks)
        # two chunks in threads: one's host work (merging maxima, pair fits) overlaps the
        # other's detection on the GPU; each thread keeps its own device buffers
        return "threads", 2, None
    if isinstance(scheduler, str) and scheduler in _LOCAL_SCHEDULERS:
        return scheduler, 1 if scheduler == "synchronous" else cores, None
    if isinstance(scheduler, str):
        if "://" not in scheduler:
            check_choice("scheduler", scheduler, (*_LOCAL_SCHEDULERS, "<address>://host:port"))
        from distributed import Client

        client = Client(scheduler)
        return client, max(1, sum(client.nthreads().values())), client
    if hasattr(scheduler, "nthreads") and hasattr(scheduler, "get"):
        return scheduler, max(1, sum(scheduler.nthreads().values())), None
    raise TypeError(
        "Expected `scheduler` to be None, 'threads', 'processes', 'synchronous', a "
        f"dask.distributed address or Client, got {type(scheduler).__name__}."
    )


def _number_pairs(table: pd.DataFrame) -> np.ndarray:
    """The ``pair`` column numbered 0, 1, ... over the table (each chunk numbers its own)."""
    pair = table["pair"].to_numpy(np.int64)
    paired = pair >= 0
    number = np.full(len(pair), -1, np.int64)
    keys = table["frame"].to_numpy(np.int64)[paired] * (int(pair.max(initial=0)) + 1)
    number[paired] = pd.factorize(keys + pair[paired])[0]
    return number


def _chunks(n_frames: int, chunk_frames: int) -> Iterator[tuple[int, int]]:
    for start in range(0, n_frames, chunk_frames):
        yield start, min(start + chunk_frames, n_frames)


def _read(frames: Any, movie: Any, start: int, stop: int) -> np.ndarray:
    """Frames ``start:stop`` as stored, read in the calling thread."""
    return np.asarray(dask.compute(_source(frames, movie, start, stop), scheduler="synchronous")[0])


def _done(function: Callable[..., Any], *args: Any) -> Future:
    """``function(*args)`` run now, in this thread, as a finished future."""
    future: Future = Future()
    future.set_result(function(*args))
    return future


def _overlapped(
    frames: Any, movie: Any, spans: list[tuple[int, int]], options: tuple, bar: tqdm
) -> list[pd.DataFrame]:
    """The tables of the chunks ``spans`` ((start, stop) frames), in order; chunk k + 1 is read
    and detected in a second thread while chunk k is fitted in this one.

    The kernels fill every core, but the host work between them (the noise's medians, merging
    maxima, fits of a few ROIs, pair fits, tables) runs on one thread: the next chunk's
    detection fills the other cores meanwhile. Two threads launching parallel kernels at once
    abort numba's "workqueue" threading layer: unless `concurrent_kernels_safe`, the chunks run
    one after another. At most two chunks are in memory."""
    camera, roi_size, threshold, method, sigma, device, calibration, pairs = options

    def detected(span: tuple[int, int]) -> tuple[np.ndarray, Detections]:
        block = _read(frames, movie, *span)
        return block, _detect_chunk(block, camera, roi_size, threshold, sigma, device)

    tables = []
    ahead = _done(detected, spans[0])
    threads = numba.get_num_threads()  # the caller's, thread-local in numba
    with ThreadPoolExecutor(1, initializer=numba.set_num_threads, initargs=(threads,)) as pool:
        submit = pool.submit if concurrent_kernels_safe() else _done
        for k, (start, stop) in enumerate(spans):
            block, found = ahead.result()
            if k + 1 < len(spans):
                ahead = submit(detected, spans[k + 1])
            tables.append(_fit_chunk(block, found, start, camera, roi_size, method, device,
                                     calibration, pairs))  # fmt: skip
            bar.update(stop - start)
    return tables


def _localize_chunks(
    frames: Any,
    movie: Any,
    chunk_frames: int,
    options: tuple,
    scheduler: Any,
    progress: bool,
    device: str,
) -> pd.DataFrame:
    """Detect and fit chunk by chunk on ``device``: with no ``scheduler`` on the CPU, each
    chunk's detection overlapping the previous chunk's fits (`_overlapped`); otherwise in waves
    of as many chunks as the scheduler has workers (`_in_waves`)."""
    spans = list(_chunks(movie.shape[0], chunk_frames))
    with tqdm(total=movie.shape[0], unit="frame", disable=not progress) as bar:
        if scheduler is None and device == "cpu":
            tables = _overlapped(frames, movie, spans, options, bar)
        else:
            tables = _in_waves(frames, movie, spans, options, scheduler, device, bar)
    return pd.concat(tables, ignore_index=True)


def _in_waves(
    frames: Any,
    movie: Any,
    spans: list[tuple[int, int]],
    options: tuple,
    scheduler: Any,
    device: str,
    bar: tqdm,
) -> list[pd.DataFrame]:
    """The tables of the chunks ``spans`` ((start, stop) frames), in order, computed by
    ``scheduler`` in waves of as many chunks as it has workers."""
    chosen, width, client = _scheduler_and_width(scheduler, device)
    # the options bound to the task's function: dask would walk the calibration's fields and
    # arrays as arguments, looking for collections, on every task
    chunk_task = dask.delayed(partial(_chunk_with, options), pure=False)
    tables = []
    try:
        for w0 in range(0, len(spans), width):
            wave = spans[w0 : w0 + width]
            tasks = [chunk_task(_source(frames, movie, a, b), a) for a, b in wave]
            tables.extend(dask.compute(*tasks, scheduler=chosen))
            bar.update(wave[-1][1] - wave[0][0])
    finally:
        if client is not None:
            client.close()
    return tables


def _settings(
    calibration: Calibration | None,
    camera: Camera | None,
    roi_size: int | None,
    method: str | None,
) -> tuple[Camera | None, int, str]:
    """The camera, ROI side (pixels) and fit method: as given, else the calibration's, else
    the defaults (no camera, 11 px, "mle")."""
    if calibration is not None:
        from latentz.calibration import Calibration

        if not isinstance(calibration, Calibration):
            raise TypeError(
                "Expected `calibration` to be a latentz Calibration, got "
                f"{type(calibration).__name__}."
            )
        camera = calibration.camera if camera is None else camera
        roi_size = calibration.roi_size if roi_size is None else roi_size
        method = calibration.method if method is None else method
    roi_size = 11 if roi_size is None else roi_size
    method = "mle" if method is None else method
    if camera is not None and not isinstance(camera, Camera):
        raise TypeError(f"Expected `camera` to be a latentz Camera, got {type(camera).__name__}.")
    return camera, roi_size, method


def _chunk_frames(
    chunk_frames: int | None, device: str, shape: tuple[int, ...], itemsize: int
) -> int:
    """Frames per chunk: as given, else as many (n, H, W) frames of ``itemsize`` bytes per
    pixel as fill the chunk's bytes (the CPU kernels read frames as stored); on the GPU, 8x
    more bytes of float64 photoelectrons."""
    if chunk_frames is None:
        if device == "cuda":
            itemsize, chunk_bytes = 8, 8 * _CHUNK_BYTES
        else:
            chunk_bytes = _CHUNK_BYTES
        chunk_frames = max(1, chunk_bytes // (itemsize * shape[1] * shape[2]))
    return check_int("chunk_frames", chunk_frames, minimum=1)


def _check_frames(
    shape: tuple[int, ...], camera: Camera | None, roi_size: int, calibration: Calibration | None
) -> None:
    """Refuse an even ROI or one larger than the frames, and a flatfield of another size."""
    check_roi_fits(roi_size, shape[1:], calibration)
    if camera is not None and camera.flatfield is not None:
        if camera.flatfield.shape != shape[1:]:
            raise ValueError(
                f"The camera's flatfield {camera.flatfield.shape} does not match the frames "
                f"{shape[1:]}."
            )


def localize(
    frames: Any,
    *,
    calibration: Calibration | None = None,
    camera: Camera | None = None,
    roi_size: int | None = None,
    threshold: float | None = None,
    method: str | None = None,
    scheduler: Any = None,
    progress: bool = False,
    sigma: float = 1.5,
    chunk_frames: int | None = None,
    track: bool = False,
    detect_every: int = 20,
    device: str = "auto",
    pairs: bool = True,
) -> pd.DataFrame:
    """Detect and fit every emitter in a movie; with a calibration, localize it in 3D.

    Parameters
    ----------
    frames : array_like (t, H, W) or (H, W), dask array, or path
        Photoelectrons if no camera is given or implied, else ADU. A path is opened lazily
        (:func:`latentz.io.as_frames`).
    calibration : Calibration, optional
        Supplies the camera, ROI size and fit method (any argument given here overrides them),
        and is applied to the spots (:meth:`~latentz.calibration.Calibration.apply`).
    camera : Camera, optional
        Converts ADU to photoelectrons (offset, gain, flatfield); its read noise enters the fit.
        Default: the calibration's, else none (frames already in photoelectrons).
    roi_size : int, optional
        Odd side of the square ROIs, in pixels. Default: the calibration's, else 11. The fitted
        widths, and so z, depend on it: a ROI other than the calibration's is warned about.
    threshold : float, optional
        Detection threshold in units of the band-passed background noise (default 5).
    method : {"mle", "wlsq", "lsq"}, optional
        Estimator, see :func:`latentz.fit.fit_rois`. Default: the calibration's, else "mle".
    scheduler : None, "threads", "processes", "synchronous", str or distributed.Client
        Where chunks run: None runs them in this process (the numba kernels use every core),
        detecting the next chunk in a second thread while this one is fitted where numba's
        threading layer allows it (docs/speed.md); a string with ``://`` is a
        dask.distributed scheduler address (a client is opened and closed here).
    progress : bool
        Show a progress bar over frames.
    sigma : float
        Smoothing scale of the detection band-pass, in pixels (about the spot width).
    chunk_frames : int, optional
        Frames per task; a few chunks (one per worker thread) are held in memory at once. The
        default keeps a chunk near 64 MB of frames as stored (8 frames of 2048 x 2048 uint16;
        512 MB of float64 on a GPU).
    device : {"auto", "cpu", "cuda"}
        Where detection and fits run (:func:`latentz._shared.engine.resolve_device`); "cuda" uses
        numba's CUDA target (extra ``latentz[gpu]``) and finds the same spots.
    track : bool
        Tracking mode (:mod:`latentz.localization.follow`): fit each emitter in the ROI predicted
        from its
        last positions, reading only those ROIs (a TIFF path is memory-mapped); detect whole
        frames every ``detect_every`` frames and wherever a fit is lost, and the frame's edge
        band on every frame. Frames run in order in this process (``scheduler`` is not used);
        ``snr`` is NaN on rows fitted from a prediction.
    detect_every : int
        Frames between full detections in tracking mode.
    pairs : bool
        Fit two emitters where one fit is shaped beyond one emitter and a second emitter is
        significant (:mod:`latentz.localization.pairs`); both are reported, with the same
        ``pair`` number. Not in tracking mode.

    Returns
    -------
    DataFrame
        `LOCALIZE_COLUMNS`: ``frame``, every column of :func:`latentz.fit.fit_rois` with ``x, y``
        in full-frame pixels (pixel ``[i, j]`` centred at ``x = j, y = i``), ``snr`` (detection
        score in noise units), ``edge`` (the ROI reaches past the frame's edge: it is clipped to
        the frame, and its pixels outside are left out of the fit), ``close_pair`` (another
        detection lies inside this ROI), ``pair`` (the number shared by the two rows of a
        two-emitter fit, −1 otherwise) and ``merged`` (shaped beyond one emitter, not split);
        with a calibration, the
        columns of :meth:`~latentz.calibration.Calibration.apply` too. Then the quality verdict
        of :func:`latentz.localization.quality.assess`: ``good`` and the flags that explain it
        (nothing is
        dropped); with a calibration that most spots contradict, one warning names the likely
        cause. Rows are ordered by frame; ``attrs["roi_size"]`` records the ROI.
    """
    movie = as_frames(frames)
    camera, roi_size, method = _settings(calibration, camera, roi_size, method)
    check_choice("method", method, METHODS)
    device = resolve_device(device)
    roi_size = check_int("roi_size", roi_size, minimum=3)
    if camera is not None:
        check_camera_offset(camera, movie)
    chunk_frames = _chunk_frames(chunk_frames, device, movie.shape, movie.dtype.itemsize)
    _check_frames(movie.shape, camera, roi_size, calibration)
    options = (camera, roi_size, threshold, method, sigma, device)
    if track:  # a tracked emitter is one bead or fiducial: no pairs
        detect_every = check_int("detect_every", detect_every, minimum=1)
        source = open_movie(frames) if isinstance(frames, str | os.PathLike) else movie
        table = localize_tracked(
            source,
            lambda t: _localize_chunk(np.asarray(source[t : t + 1]), t, *options),
            camera=camera, roi_size=roi_size, threshold=threshold, method=method, sigma=sigma,
            detect_every=detect_every, progress=progress,
        )  # fmt: skip
    else:
        table = _localize_chunks(
            frames, movie, chunk_frames, (*options, calibration, bool(pairs)), scheduler,
            progress, device,
        )  # fmt: skip
        table["pair"] = _number_pairs(table)
    table.attrs["roi_size"] = roi_size
    if calibration is not None:
        table = calibration.apply(with_truncation_errors(table, movie.shape[1:]))
    table = with_crowding_errors(assess(table, calibration), movie.shape[1:])
    if calibration is not None:
        table = check_calibration_fits(table, calibration)
    return table

"""Images: TIFF and OME-TIFF stacks and movies, read lazily.

A file becomes a dask array over tifffile's zarr store, so movies larger than memory are read plane
by plane.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import dask.array as da
import numpy as np

from latentz._shared.validate import check_array

__all__ = ["read_stack", "open_movie", "read_frames", "as_frames"]

_TIFF_SUFFIXES = (".tif", ".tiff", ".ome.tif", ".ome.tiff")


def read_stack(path: str | os.PathLike) -> da.Array:
    """Open a TIFF / OME-TIFF stack or movie lazily as a dask array of shape (n, H, W).

    A single 2D image becomes shape (1, H, W). Higher-rank files (for example T, Z, H, W) are
    refused with a clear error rather than guessed at.
    """
    import tifffile
    import zarr

    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"No such image file: {source}")
    if not source.name.lower().endswith(_TIFF_SUFFIXES):
        raise ValueError(f"Expected a .tif/.tiff image file, got {source.name!r}.")
    if source.stat().st_size == 0:
        raise ValueError(f"{source.name} is empty (0 bytes): give a TIFF stack of images.")
    try:
        with tifffile.TiffFile(source) as tif:
            if not tif.series:
                raise ValueError("no image series found")
            if 0 in tif.series[0].shape:
                raise _Empty(f"{source.name} holds no images: give a TIFF stack of images.")
            series = tif.series[0]
            shape, dtype = series.shape, series.dtype
            if series.axes.endswith("S"):  # interleaved colour samples: (..., rows, cols, 3)
                raise _Empty(
                    f"{source.name} holds colour (RGB) images of shape {tuple(shape)}: latentz "
                    "needs single-channel frames; save the camera's raw grayscale frames."
                )
            _check_complete(tif, series, source)
        store = tifffile.imread(source, aszarr=True)
        array = da.from_zarr(zarr.open(store, mode="r"))
    except _Empty:
        raise
    except (tifffile.TiffFileError, ValueError, OSError, KeyError, IndexError) as exc:
        raise ValueError(f"Cannot read {source.name} as a TIFF stack: {exc}") from exc
    if array.shape != tuple(shape) or array.dtype != dtype:
        raise ValueError(f"{source.name}: inconsistent TIFF series {shape} {dtype}.")
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3:
        raise ValueError(
            f"Expected {source.name} to hold a (frames, rows, columns) stack, got shape "
            f"{array.shape}."
        )
    return array


def open_movie(path: str | os.PathLike) -> np.ndarray | da.Array:
    """A TIFF movie (n, H, W): memory-mapped when contiguous and uncompressed, so indexing reads
    only the bytes it touches (a frame range, or a few ROIs of a frame); otherwise the lazy dask
    array of :func:`read_stack`."""
    import tifffile

    stack = read_stack(path)  # and its checks: exists, a TIFF, complete, 2D or 3D
    try:
        frames = tifffile.memmap(path, mode="r")
    except ValueError:  # compressed or not contiguous
        return stack
    return frames[None] if frames.ndim == 2 else frames


def read_frames(path: str | os.PathLike, start: int, stop: int) -> np.ndarray:
    """Frames ``start:stop`` of a TIFF movie as a numpy array (file dtype), opened here.

    Opening the file in the caller is what lets a dask.distributed worker read its own frames:
    a task then carries only the path and the range.
    """
    return np.asarray(open_movie(path)[start:stop])


class _Empty(ValueError):
    """A readable TIFF that holds nothing latentz can use (its message says why and the fix)."""


def _check_complete(tif, series, source: Path) -> None:
    """Refuse a truncated file: every page's image data must lie inside the file."""
    size = source.stat().st_size
    if series.dataoffset is not None:  # contiguous data: one check covers every page
        if series.dataoffset + series.nbytes > size:
            raise ValueError(f"{source.name} is truncated (image data beyond the file end).")
        return
    for page in tif.pages:
        ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts, strict=True)]
        if not ends or max(ends) > size or 0 in page.databytecounts:
            raise ValueError(f"{source.name} is truncated (page data beyond the file end).")


def as_frames(frames: Any, *, name: str = "frames") -> da.Array | np.ndarray:
    """Return ``frames`` as a 3D array (n, H, W): numpy stays numpy, dask stays lazy, a path is
    opened lazily with :func:`read_stack`. A 2D image gains a leading axis of length 1."""
    if isinstance(frames, str | os.PathLike):
        return read_stack(frames)
    if isinstance(frames, da.Array):
        array = frames
        if array.dtype.kind not in "uif":
            raise TypeError(f"Expected `{name}` to have a numeric dtype, got {array.dtype}.")
    else:
        array = check_array(name, frames, ndim=(2, 3), dtype_kind="uif")
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3:
        raise ValueError(f"Expected `{name}` to have 2 or 3 dimensions, got shape {array.shape}.")
    if min(array.shape) == 0:
        raise ValueError(f"Expected `{name}` to be non-empty, got shape {array.shape}.")
    return array

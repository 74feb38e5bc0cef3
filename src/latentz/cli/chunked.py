"""Resumable, chunk-by-chunk processing of long movies into one table.

Each finished chunk is written atomically into a work folder beside the output
(``<out>.chunks/``), with a manifest that pins the inputs and options. The output file appears,
atomically, only when every chunk is done; then the work folder is removed. A run killed at any
moment therefore leaves no partial output, and ``resume=True`` carries on from the last finished
chunk when the manifest matches.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from latentz._shared.atomic import write_text_atomic
from latentz._shared.validate import check_int
from latentz.io import read_table, write_table

__all__ = ["run_chunked", "chunk_dir"]


def chunk_dir(out: str | os.PathLike) -> Path:
    """The work folder that holds the finished chunks of ``out``."""
    target = Path(out)
    return target.with_name(target.name + ".chunks")


def _prepare(work: Path, manifest: dict[str, Any], resume: bool) -> None:
    manifest_path = work / "manifest.json"
    wanted = json.dumps(manifest, sort_keys=True, default=str)
    if work.exists():
        found = manifest_path.read_text() if manifest_path.exists() else None
        if resume and found == wanted:
            return
        if resume and found is not None:
            raise ValueError(
                f"Cannot resume: {work} was made with other inputs or options; "
                "run again without --resume to start over."
            )
        shutil.rmtree(work)
    work.mkdir(parents=True)
    write_text_atomic(manifest_path, wanted)


def run_chunked(
    n_frames: int,
    process: Callable[[int, int], pd.DataFrame],
    out: str | os.PathLike,
    *,
    manifest: dict[str, Any],
    chunk_frames: int = 100,
    resume: bool = False,
    metadata: dict[str, Any] | None = None,
    progress: bool = False,
    finish: Callable[[pd.DataFrame], pd.DataFrame] | None = None,
) -> pd.DataFrame:
    """Run ``process(start, stop)`` over frame chunks and write the concatenated table to ``out``.

    Parameters
    ----------
    n_frames : int
        Number of frames in the movie.
    process : callable
        Returns the table for frames ``start`` to ``stop`` (exclusive).
    out : path
        Parquet or CSV output, written atomically with ``metadata`` once all chunks are done.
    manifest : dict
        What identifies the job (input names, sizes, hashes, options); a resumed run must match.
    chunk_frames : int
        Frames per chunk; bounds memory.
    resume : bool
        Reuse the finished chunks of an interrupted run with the same manifest.
    finish : callable, optional
        Applied to the whole table before it is written (checks that need every chunk).
    """
    n_frames = check_int("n_frames", n_frames, minimum=1)
    chunk_frames = check_int("chunk_frames", chunk_frames, minimum=1)
    work = chunk_dir(out)
    _prepare(work, manifest, resume)
    starts = range(0, n_frames, chunk_frames)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(starts), unit="chunk", desc="localize")
    parts = []
    try:
        for start in starts:
            stop = min(start + chunk_frames, n_frames)
            piece = work / f"chunk-{start:09d}-{stop:09d}.parquet"
            if piece.exists():
                table, _ = read_table(piece)
            else:
                table = process(start, stop)
                write_table(table, piece)
            parts.append(table)
            if bar is not None:
                bar.update()
    except Exception:
        if not any(work.glob("chunk-*.parquet")):  # nothing to resume from: leave no trace
            shutil.rmtree(work, ignore_errors=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    non_empty = [p for p in parts if len(p)]
    result = pd.concat(non_empty, ignore_index=True) if non_empty else parts[0]
    if finish is not None:
        result = finish(result)
    write_table(result, out, metadata=metadata)
    shutil.rmtree(work)
    return result

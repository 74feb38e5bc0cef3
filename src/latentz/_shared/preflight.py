"""Checks the CLI runs before any long work: where outputs go, and what they are called."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["check_output_file", "check_output_folder"]


def _check_folder_writable(folder: Path, option: str) -> None:
    if not folder.is_dir():
        raise ValueError(
            f"The folder {folder} of {option} does not exist: create it first, or choose "
            "another path."
        )
    try:  # a real write: permission bits do not tell for root, read-only mounts or /proc
        with tempfile.TemporaryFile(dir=folder, prefix=".latentz-probe-"):
            pass
    except OSError as exc:
        raise ValueError(
            f"Cannot write into {folder} ({exc.strerror or exc}): choose another {option} path."
        ) from exc


def check_output_file(path: str | os.PathLike, suffixes: tuple[str, ...], *, option: str = "--out"):
    """Refuse an output file whose suffix is not one of ``suffixes`` or whose folder does not
    exist or cannot be written, naming the fix."""
    target = Path(path)
    if not target.name.lower().endswith(suffixes):
        listed = ", ".join(suffixes)
        raise ValueError(
            f"Cannot tell what to write from the name {target.name!r} of {option}: use a "
            f"name ending in {listed}."
        )
    if target.is_dir():
        raise ValueError(f"{option} {target} is a folder: give a file name.")
    _check_folder_writable(target.parent if str(target.parent) else Path("."), option)


def check_output_folder(path: str | os.PathLike, *, option: str = "--out") -> None:
    """Refuse an output folder that cannot be made or written: its parent must exist and be
    writable (a folder that exists must be writable itself)."""
    target = Path(path)
    if target.exists():
        if not target.is_dir():
            raise ValueError(f"{option} {target} is a file: give a folder.")
        _check_folder_writable(target, option)
        return
    _check_folder_writable(target.parent if str(target.parent) else Path("."), option)

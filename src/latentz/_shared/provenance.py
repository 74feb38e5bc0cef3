"""Provenance: what every output records about how it was made (inputs' digests, options,
version, date)."""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from pathlib import Path
from typing import Any

from latentz._version import __version__

__all__ = ["file_digest", "stamp", "provenance"]


def file_digest(path: str | os.PathLike, *, block: int = 1 << 20) -> str:
    """SHA-256 of a file, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(block):
            digest.update(chunk)
    return digest.hexdigest()


def stamp() -> dict[str, str]:
    """The latentz version and the date and time now (UTC, ISO 8601), for output metadata."""
    return {
        "latentz_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }


def provenance(inputs: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """Metadata that every output carries: inputs (name, size, SHA-256), options, version, date."""
    described = {}
    for role, paths in inputs.items():
        items = [paths] if isinstance(paths, str | os.PathLike) else list(paths)
        described[role] = [
            {"name": str(p), "bytes": Path(p).stat().st_size, "sha256": file_digest(p)}
            for p in items
        ]
    return {**stamp(), "inputs": described, "options": options}

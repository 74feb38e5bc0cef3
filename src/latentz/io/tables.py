"""Tables: localizations and motion written atomically to Parquet or CSV, with metadata."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pandas as pd

from latentz._shared.atomic import atomic_path, write_text_atomic

__all__ = ["TABLE_FORMATS", "write_table", "read_table"]

TABLE_FORMATS = ("parquet", "csv")


def _format_of(path: Path, fmt: str | None) -> str:
    if fmt is not None:
        if fmt not in TABLE_FORMATS:
            raise ValueError(f"Expected `fmt` to be one of {TABLE_FORMATS}, got {fmt!r}.")
        return fmt
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".pq"):
        return "parquet"
    if suffix == ".csv":
        return "csv"
    raise ValueError(f"Cannot tell the table format of {path.name!r}: use .parquet or .csv.")


def write_table(
    table: pd.DataFrame,
    path: str | os.PathLike,
    *,
    fmt: str | None = None,
    metadata: dict[str, Any] | None = None,
) -> Path:
    """Write ``table`` atomically to Parquet or CSV (chosen by ``fmt`` or the suffix).

    ``metadata`` (JSON-serialisable, e.g. provenance) is stored in the Parquet schema under the key
    ``latentz``; for CSV it goes to a sidecar ``<path>.json`` written atomically as well.
    """
    target = Path(path)
    kind = _format_of(target, fmt)
    if not isinstance(table, pd.DataFrame):
        raise TypeError(f"Expected `table` to be a pandas DataFrame, got {type(table).__name__}.")
    with atomic_path(target) as tmp:
        if kind == "parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            arrow = pa.Table.from_pandas(table, preserve_index=False)
            if metadata:
                meta = dict(arrow.schema.metadata or {})
                meta[b"latentz"] = json.dumps(metadata, default=str).encode()
                arrow = arrow.replace_schema_metadata(meta)
            pq.write_table(arrow, tmp)
        else:
            table.to_csv(tmp, index=False)
    if metadata and kind == "csv":
        write_text_atomic(
            target.with_name(target.name + ".json"), json.dumps(metadata, indent=2, default=str)
        )
    return target


def read_table(path: str | os.PathLike, *, fmt: str | None = None) -> tuple[pd.DataFrame, dict]:
    """Read a table written by :func:`write_table`; return it with its latentz metadata."""
    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"No such table file: {source}")
    kind = _format_of(source, fmt)
    try:
        if kind == "parquet":
            import pyarrow.parquet as pq

            arrow = pq.read_table(source)
            raw = (arrow.schema.metadata or {}).get(b"latentz")
            return arrow.to_pandas(), (json.loads(raw) if raw else {})
        sidecar = source.with_name(source.name + ".json")
        meta = json.loads(sidecar.read_text()) if sidecar.exists() else {}
        return pd.read_csv(source), meta
    except (OSError, ValueError) as exc:
        raise ValueError(f"Cannot read table {source.name}: {exc}") from exc

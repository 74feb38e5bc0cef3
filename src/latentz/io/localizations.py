"""Localization tables in any format latentz knows, read into latentz's columns (x_nm, y_nm,
z_nm, their errors, frame): latentz Parquet or CSV, Picasso HDF5, ThunderSTORM CSV."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from latentz._shared.validate import check_columns
from latentz.io.picasso import read_picasso
from latentz.io.tables import read_table
from latentz.io.thunderstorm import is_thunderstorm, read_thunderstorm

__all__ = ["read_localizations", "LOCALIZATION_SUFFIXES"]

LOCALIZATION_SUFFIXES = (".parquet", ".pq", ".csv", ".hdf5", ".h5")


def read_localizations(
    path: str | os.PathLike, *, pixel_size_nm: float | None = None
) -> tuple[pd.DataFrame, dict]:
    """Read a localization file by its suffix and header; return the table and its metadata.

    ``.hdf5``/``.h5``: Picasso (``pixel_size_nm`` overrides its YAML's); ``.csv``: ThunderSTORM
    when its header has "x [nm]", else latentz's CSV; ``.parquet``: latentz's."""
    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"No such localization file: {source}")
    suffix = source.suffix.lower()
    if suffix not in LOCALIZATION_SUFFIXES:
        raise ValueError(
            f"Cannot tell the format of {source.name!r}: give latentz .parquet/.csv, Picasso "
            ".hdf5 or ThunderSTORM .csv."
        )
    if suffix in (".hdf5", ".h5"):
        table, meta = read_picasso(source, pixel_size_nm=pixel_size_nm), {"format": "picasso"}
    elif suffix == ".csv" and is_thunderstorm(pd.read_csv(source, nrows=0).columns):
        table, meta = read_thunderstorm(source), {"format": "thunderstorm"}
    else:
        table, meta = read_table(source)
    check_columns(source.name, table, ("frame", "x_nm", "y_nm"))
    return table, meta

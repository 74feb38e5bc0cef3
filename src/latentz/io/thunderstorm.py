"""ThunderSTORM's localization CSV (the ImageJ plugin's "Export results"): quoted headers with
units, positions and widths in nm, intensities in photons, frames counted from 1.

latentz writes the 3D (astigmatism) layout: "id", "frame", "x [nm]", "y [nm]", "z [nm]",
"sigma1 [nm]", "sigma2 [nm]", "intensity [photon]", "offset [photon]", "bkgstd [photon]",
"uncertainty_xy [nm]", "uncertainty_z [nm]"; it reads that layout and the 2D one ("sigma [nm]",
"uncertainty [nm]" or "uncertainty_xy [nm]")."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import atomic_path
from latentz._shared.validate import check_columns, check_positive

__all__ = ["THUNDERSTORM_COLUMNS", "write_thunderstorm", "read_thunderstorm", "is_thunderstorm"]

THUNDERSTORM_COLUMNS = (
    "id",
    "frame",
    "x [nm]",
    "y [nm]",
    "z [nm]",
    "sigma1 [nm]",
    "sigma2 [nm]",
    "intensity [photon]",
    "offset [photon]",
    "bkgstd [photon]",
    "uncertainty_xy [nm]",
    "uncertainty_z [nm]",
)

#: latentz columns that ThunderSTORM's file needs.
_NEEDED = (
    "frame",
    "x_nm",
    "y_nm",
    "z_nm",
    "wx",
    "wy",
    "photons",
    "background",
    "x_err_nm",
    "y_err_nm",
    "z_err_nm",
)


def write_thunderstorm(
    locs: pd.DataFrame, path: str | os.PathLike, *, pixel_size_nm: float
) -> Path:
    """Write ``locs`` as ThunderSTORM CSV, atomically.

    Positions and errors are latentz's (nm); sigma1, sigma2 are the fitted widths wx, wy in nm
    (``pixel_size_nm``); offset is the background per pixel and bkgstd its Poisson spread, in
    photons; uncertainty_xy is the mean of the x and y errors. Frames are counted from 1. Rows
    outside the calibrated range keep z = NaN (written as an empty field)."""
    check_columns("locs", locs, _NEEDED)
    pixel = check_positive("pixel_size_nm", pixel_size_nm)
    background = locs["background"].to_numpy(dtype=np.float64)
    table = pd.DataFrame(
        {
            "id": np.arange(1, len(locs) + 1),
            "frame": locs["frame"].to_numpy().astype(np.int64) + 1,
            "x [nm]": locs["x_nm"].to_numpy(),
            "y [nm]": locs["y_nm"].to_numpy(),
            "z [nm]": locs["z_nm"].to_numpy(),
            "sigma1 [nm]": locs["wx"].to_numpy() * pixel,
            "sigma2 [nm]": locs["wy"].to_numpy() * pixel,
            "intensity [photon]": locs["photons"].to_numpy(),
            "offset [photon]": background,
            "bkgstd [photon]": np.sqrt(np.clip(background, 0, None)),
            "uncertainty_xy [nm]": (locs["x_err_nm"].to_numpy() + locs["y_err_nm"].to_numpy()) / 2,
            "uncertainty_z [nm]": locs["z_err_nm"].to_numpy(),
        }
    )
    target = Path(path)
    if target.suffix.lower() != ".csv":
        raise ValueError(f"ThunderSTORM files end in .csv, got {target.name!r}.")
    with atomic_path(target) as tmp:
        table.to_csv(tmp, index=False, quoting=csv.QUOTE_NONNUMERIC, float_format="%.6g")
    return target


def is_thunderstorm(columns) -> bool:
    """Whether a CSV's header is ThunderSTORM's (positions as "x [nm]", "y [nm]")."""
    return {"x [nm]", "y [nm]"} <= set(columns)


def _first(table: pd.DataFrame, *names: str) -> np.ndarray:
    for name in names:
        if name in table:
            return table[name].to_numpy(dtype=np.float64)
    return np.full(len(table), np.nan)


def read_thunderstorm(path: str | os.PathLike) -> pd.DataFrame:
    """A ThunderSTORM CSV as a latentz table: frame (from 0), x_nm, y_nm, z_nm (NaN for 2D),
    x_err_nm = y_err_nm (the lateral uncertainty), z_err_nm, photons, background, sigma1_nm,
    sigma2_nm, and ``in_range`` (a z was measured)."""
    table = pd.read_csv(path)
    if not is_thunderstorm(table.columns) or "frame" not in table:
        raise ValueError(
            f'{Path(path).name} is not a ThunderSTORM CSV: it needs the columns "frame", '
            '"x [nm]", "y [nm]".'
        )
    lateral = _first(table, "uncertainty_xy [nm]", "uncertainty [nm]")
    z = _first(table, "z [nm]")
    return pd.DataFrame(
        {
            "frame": table["frame"].to_numpy().astype(np.int64) - 1,
            "x_nm": table["x [nm]"].to_numpy(dtype=np.float64),
            "y_nm": table["y [nm]"].to_numpy(dtype=np.float64),
            "z_nm": z,
            "x_err_nm": lateral,
            "y_err_nm": lateral,
            "z_err_nm": _first(table, "uncertainty_z [nm]"),
            "photons": _first(table, "intensity [photon]"),
            "background": _first(table, "offset [photon]"),
            "sigma1_nm": _first(table, "sigma1 [nm]", "sigma [nm]"),
            "sigma2_nm": _first(table, "sigma2 [nm]", "sigma [nm]"),
            "in_range": np.isfinite(z),
        }
    )

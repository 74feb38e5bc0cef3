"""napari layers from latentz files, as napari's LayerData tuples ``(data, kwargs, kind)``, built
without importing napari (napari calls :func:`get_reader`; the tests call the rest)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["get_reader", "layers_of_localizations", "layers_of_calibration"]

LayerData = tuple[Any, dict[str, Any], str]

#: Error and quality columns shown as each point's features, where the table has them.
_FEATURES = ("frame", "z_nm", "x_err_nm", "y_err_nm", "z_err_nm", "photons", "good")

#: Side of the interpolated field maps, pixels.
_MAP_SIDE = 256


def layers_of_localizations(locs: pd.DataFrame, *, name: str) -> list[LayerData]:
    """One 3D points layer (z, y, x in nm) coloured by z (turbo), each point sized by its
    lateral error (2 sigma, at least 10 nm), with the error columns as features. Rows without a
    finite x, y, z are left out."""
    xyz = locs[["x_nm", "y_nm", "z_nm"]].to_numpy(dtype=np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    used = locs[finite]
    features = used[[c for c in _FEATURES if c in used]].reset_index(drop=True)
    lateral = used["x_err_nm"].to_numpy() if "x_err_nm" in used else np.full(len(used), 5.0)
    kwargs = {
        "name": name,
        "ndim": 3,
        "features": features,
        "face_color": "z_nm",
        "face_colormap": "turbo",
        "size": np.maximum(2 * lateral, 10.0),
        "units": "nm",
    }
    return [(xyz[finite][:, ::-1].copy(), kwargs, "points")]


def _field_map(xy_nm: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, tuple, tuple]:
    """``values`` at the particles interpolated linearly over the field they span: image,
    scale (nm per pixel, rows and columns) and translate (nm)."""
    from scipy.interpolate import griddata

    lo, hi = xy_nm.min(axis=0), xy_nm.max(axis=0)
    step = float(max(hi - lo)) / (_MAP_SIDE - 1)
    cols = np.arange(lo[0], hi[0] + step / 2, step)
    rows = np.arange(lo[1], hi[1] + step / 2, step)
    grid_x, grid_y = np.meshgrid(cols, rows)
    image = griddata(xy_nm, values, (grid_x, grid_y), method="linear")
    return image, (step, step), (float(lo[1]), float(lo[0]))


def layers_of_calibration(cal, *, name: str) -> list[LayerData]:
    """The calibration particles as 2D points (y, x in nm; culled ones grey with their reason)
    and two images interpolated linearly between the kept particles: best focus after tilt
    removal (the field curvature, nm) and sigma_z of the calibration's shape (nm)."""
    table = cal.particles
    xy = table[["x_nm", "y_nm"]].to_numpy(dtype=np.float64)
    culled = table["culled"].to_numpy(dtype=bool)
    features = pd.DataFrame(
        {
            "particle": table["particle"].to_numpy(),
            "z_f_nm": table["z_f_nm"].to_numpy(),
            "sigma_z_nm": table["sigma_z"].to_numpy(),
            "culled": culled,
            "reason": table["reason"].astype(str).to_numpy(),
        }
    )
    points = (
        xy[:, ::-1].copy(),
        {
            "name": f"{name} particles",
            "features": features,
            "face_color": np.where(culled[:, None], [[0.5, 0.5, 0.5, 1.0]], [[1.0, 1.0, 1.0, 1.0]]),
            "size": 400.0,
            "units": "nm",
        },
        "points",
    )
    layers = [points]
    kept = ~culled & np.isfinite(table["z_f_nm"]).to_numpy()
    if kept.sum() >= 3:
        for column, label, colormap in (
            ("z_f_nm", "best focus z (nm)", "turbo"),
            ("sigma_z", "sigma_z (nm)", "magma"),
        ):
            image, scale, translate = _field_map(xy[kept], table[column].to_numpy()[kept])
            kwargs = {
                "name": f"{name} {label}",
                "scale": scale,
                "translate": translate,
                "colormap": colormap,
                "units": "nm",
            }
            layers.insert(0, (image, kwargs, "image"))
    return layers


def _read(path: str | os.PathLike) -> list[LayerData]:
    from latentz.io import read_localizations

    source = Path(path)
    if source.suffix.lower() in (".h5", ".hdf5") and not _is_picasso(source):
        from latentz.calibration import Calibration

        return layers_of_calibration(Calibration.load(source), name=source.stem)
    locs, _ = read_localizations(source)
    return layers_of_localizations(locs, name=source.stem)


def _is_picasso(path: Path) -> bool:
    import h5py

    with h5py.File(path, "r") as handle:
        return "locs" in handle


def get_reader(path: str | list[str]) -> Callable[[str], list[LayerData]] | None:
    """napari's reader hook: a function that reads ``path`` into layers, or None for a path
    latentz does not read (a list of paths, or another suffix)."""
    if isinstance(path, list):
        return None
    if Path(path).suffix.lower() not in (".parquet", ".pq", ".csv", ".hdf5", ".h5"):
        return None
    return _read

"""Super-resolution rendering: an RGB picture of the localizations, brightness from their density,
colour from z, blurred by each one's reported error; a top (x-y) and a side (x-z) view with a
scale bar and a z colour bar. Also the float images behind it, for a TIFF with its pixel size."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.validate import check_choice, check_positive
from latentz.analysis.histograms import Grid, grid_for, positions, splat

__all__ = ["render", "density_images", "write_render", "RENDER_SUFFIXES"]

RENDER_SUFFIXES = (".png", ".tif", ".tiff")

#: The brightest pixels (this percentile of the occupied ones) saturate.
_SATURATION_PERCENTILE = 99.5
_COLOURBAR_PX = 110
_SIDE_ROWS = 80
_GAP_PX = 8


def _widths(
    locs: pd.DataFrame, blur: str | float | None, column: str, pixel_nm: float
) -> np.ndarray | None:
    """Each localization's blur (nm), at least one pixel so that every one shows."""
    if blur is None:
        return None
    if isinstance(blur, str):
        check_choice("blur", blur, ("precision",))
        return np.maximum(locs[column].to_numpy(), pixel_nm)
    return np.full(len(locs), max(check_positive("blur", blur), pixel_nm))


def z_stretch(z_nm: np.ndarray, pixel_nm: float) -> float:
    """How much the side view stretches z so that it is at least 80 pixels tall (1: none)."""
    span = float(np.ptp(z_nm)) if len(z_nm) else 0.0
    return max(1.0, _SIDE_ROWS * pixel_nm / max(span, pixel_nm))


def _margin_nm(su: np.ndarray | None, sv: np.ndarray | None, pixel_nm: float) -> float:
    """Room around the localizations for their blur: 3 median widths, at least 2 pixels."""
    widths = [np.median(s) for s in (su, sv) if s is not None and len(s)]
    return max([3.0 * w for w in widths] + [2.0 * pixel_nm])


def _rows(locs: pd.DataFrame, color: str | None, blur: str | float | None) -> pd.DataFrame:
    columns = ["x_nm", "y_nm", "z_nm"]
    if blur == "precision":
        columns += ["x_err_nm", "y_err_nm", "z_err_nm"]
    if color is not None and color not in columns:
        columns.append(color)
    return positions(locs, tuple(columns))


def density_images(
    locs: pd.DataFrame,
    *,
    pixel_nm: float = 10.0,
    blur: str | float | None = "precision",
    color: str | None = "z_nm",
    extent: tuple[float, float, float, float] | None = None,
) -> dict[str, tuple[Grid, np.ndarray, np.ndarray | None]]:
    """The float images behind :func:`render`: for each view ("xy", "xz") its grid, density
    (localizations per pixel, blurred) and the density-weighted mean of ``color`` per pixel
    (None without colour). ``extent`` = (x_min, x_max, y_min, y_max) in nm. The side view's
    z is stretched by :func:`z_stretch` (its rows are ``pixel_nm / z_stretch`` nm of z)."""
    used = _rows(locs, color, blur)
    x, y, z = (used[c].to_numpy() for c in ("x_nm", "y_nm", "z_nm"))
    sx, sy = (_widths(used, blur, f"{a}_err_nm", pixel_nm) for a in "xy")
    stretch = z_stretch(z, pixel_nm)
    sz = _widths(used, blur, "z_err_nm", pixel_nm / stretch)
    z = z * stretch
    sz = None if sz is None else sz * stretch
    margin = _margin_nm(sx, sy, pixel_nm) if extent is None else 0.0
    top = grid_for(x, y, pixel_nm, extent=extent, margin_nm=margin)
    z_margin = _margin_nm(sz, sz, pixel_nm)
    z_lo, z_hi = (np.min(z) - z_margin, np.max(z) + z_margin) if len(z) else (0.0, 1.0)
    depth = grid_for(x, z, pixel_nm, extent=(top.u0, top.u0 + pixel_nm, z_lo, z_hi))
    side = replace(top, v0=depth.v0, n_v=depth.n_v)  # the same x pixels as the top view
    views = {}
    for name, grid, (u, v, su, sv) in (
        ("xy", top, (x, y, sx, sy)),
        ("xz", side, (x, z, sx, sz)),
    ):
        dens = splat(grid, u, v, sigma_u_nm=su, sigma_v_nm=sv)
        mean = None
        if color is not None:
            weighted = splat(grid, u, v, sigma_u_nm=su, sigma_v_nm=sv, weights=used[color])
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(dens > 0, weighted / dens, np.nan)
        views[name] = (grid, dens, mean)
    return views


def _colour(dens: np.ndarray, mean: np.ndarray | None, norm, cmap, top: float) -> np.ndarray:
    """RGB floats in [0, 1]: brightness from density (saturating at ``top``), hue from ``mean``."""
    bright = np.clip(dens / top, 0.0, 1.0)[..., None]
    if mean is None:
        return np.repeat(bright, 3, axis=2)
    hue = cmap(norm(np.nan_to_num(mean, nan=norm.vmin)))[..., :3]
    return hue * bright


def _scale_bar_nm(width_nm: float) -> float:
    """A round length (1, 2 or 5 x 10^k nm) near a fifth of the width."""
    target = width_nm / 5
    power = 10 ** np.floor(np.log10(target))
    return float(max(m * power for m in (1, 2, 5) if m * power <= target))


def _bar_label(length_nm: float) -> str:
    return f"{length_nm / 1e3:g} µm" if length_nm >= 1000 else f"{length_nm:g} nm"


def render(
    locs: pd.DataFrame,
    *,
    pixel_nm: float = 10.0,
    color: str | None = "z",
    blur: str | float | None = "precision",
    extent: tuple[float, float, float, float] | None = None,
    z_range: tuple[float, float] | None = None,
) -> np.ndarray:
    """An RGB picture (uint8, rows x columns x 3) of the localizations.

    Top left, pixel for pixel, the x-y view: ``pixel_nm`` per pixel over ``extent`` = (x_min,
    x_max, y_min, y_max) in nm (default: all the localizations), y down as in the camera
    image. Below it the x-z side view on the same x axis, z up. Brightness is the number of
    localizations per pixel (saturating at the brightest 0.5 %); colour is ``color`` ("z", or
    any column; None for grey). ``blur``: "precision" draws each localization as a Gaussian of
    its own reported error (``x_err_nm``, ``y_err_nm``, ``z_err_nm``), a number a fixed width
    in nm, None a histogram. A scale bar sits in the x-y view, a colour bar on the right
    spans ``z_range`` (default: the 1st to 99th percentile). Rows without a finite position
    (e.g. out of the calibrated range) are not drawn.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    check_choice("blur", blur, ("precision",)) if isinstance(blur, str) else None
    column = {"z": "z_nm"}.get(color, color) if color is not None else None
    views = density_images(locs, pixel_nm=pixel_nm, blur=blur, color=column, extent=extent)
    (top_grid, top, top_mean), (side_grid, side, side_mean) = views["xy"], views["xz"]
    values = _rows(locs, column, blur)
    if column is not None and z_range is None:
        z_range = tuple(np.percentile(values[column], [1, 99])) if len(values) else (0.0, 1.0)
    norm = Normalize(*(z_range if column is not None else (0.0, 1.0)))
    cmap = plt.get_cmap("turbo")
    occupied = np.concatenate([top[top > 0], side[side > 0]])
    peak = np.percentile(occupied, _SATURATION_PERCENTILE) if occupied.size else 1.0
    # the side view has z up: flip its rows
    panels = (
        _colour(top, top_mean, norm, cmap, peak),
        _colour(side, side_mean, norm, cmap, peak)[::-1],
    )
    height = top.shape[0] + _GAP_PX + side.shape[0]
    width = top.shape[1] + _COLOURBAR_PX
    dpi = 100
    fig = plt.figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="black")
    fig.figimage(panels[0], xo=0, yo=height - top.shape[0], origin="upper")
    fig.figimage(panels[1], xo=0, yo=0, origin="upper")
    stretch = z_stretch(values["z_nm"].to_numpy(), pixel_nm) if len(values) else 1.0
    _annotate(fig, top_grid, side_grid, height, column, norm, cmap, stretch)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb


def _annotate(fig, top: Grid, side: Grid, height: int, column, norm, cmap, stretch) -> None:
    """Scale bar and view names (pixel positions), and the colour bar at the right."""
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.patches import Rectangle

    width_nm = top.n_u * top.pixel_nm
    bar_nm = _scale_bar_nm(width_nm)
    bar_px = bar_nm / top.pixel_nm
    y_bar = height - top.n_v + 12
    fig.patches.append(Rectangle((10, y_bar), bar_px, 4, transform=None, color="white", figure=fig))
    text = {"color": "white", "fontsize": 8, "transform": None}
    fig.text(10, y_bar + 8, _bar_label(bar_nm), **text)
    fig.text(6, height - 14, "x–y", **text)
    side_name = "x–z (z up)" if stretch == 1 else f"x–z (z up, stretched ×{stretch:.3g})"
    fig.text(6, side.n_v - 14, side_name, **text)
    if column is None:
        return
    figure_w, figure_h = fig.get_size_inches() * fig.dpi
    axis = fig.add_axes([(top.n_u + 30) / figure_w, 0.1, 18 / figure_w, 0.8])
    bar = ColorbarBase(axis, cmap=cmap, norm=norm)
    bar.set_label("z (nm)" if column == "z_nm" else column, color="white", fontsize=8)
    bar.ax.tick_params(colors="white", labelsize=7)
    bar.outline.set_edgecolor("white")


def write_render(
    locs: pd.DataFrame,
    path: str | os.PathLike,
    *,
    pixel_nm: float = 10.0,
    color: str | None = "z",
    blur: str | float | None = "precision",
) -> Path:
    """Write the rendering atomically: ``.png`` the RGB picture of :func:`render`; ``.tif`` the
    float x-y images (ImageJ hyperstack, channel 1 density, channel 2 mean z in nm) with the
    pixel size in nm in the TIFF resolution tags and ImageJ metadata."""
    from latentz._shared.atomic import atomic_path

    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in RENDER_SUFFIXES:
        raise ValueError(f"Render to .png or .tif, got {target.name!r}.")
    if suffix == ".png":
        import matplotlib.image

        rgb = render(locs, pixel_nm=pixel_nm, color=color, blur=blur)
        with atomic_path(target) as tmp:
            matplotlib.image.imsave(tmp, rgb, format="png")
        return target
    import tifffile

    column = {"z": "z_nm"}.get(color, color) if color is not None else "z_nm"
    _, dens, mean = density_images(locs, pixel_nm=pixel_nm, blur=blur, color=column)["xy"]
    stack = np.stack([dens, mean]).astype(np.float32)
    with atomic_path(target) as tmp:
        tifffile.imwrite(
            tmp,
            stack,
            imagej=True,
            resolution=(1.0 / pixel_nm, 1.0 / pixel_nm),
            metadata={"axes": "CYX", "unit": "nm", "Labels": ["density", column]},
        )
    return target

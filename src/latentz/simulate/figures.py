"""Figures of the simulated microscope: the PSF gallery (x–z and x–y sections through focus)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from latentz._shared.atomic import atomic_path
from latentz.simulate._render import patch_size_px
from latentz.simulate.aberrations import AberrationMap
from latentz.simulate.optics import Optics

__all__ = ["psf_gallery", "save_psf_gallery"]


def psf_gallery(
    optics: Optics | None = None,
    aberrations: AberrationMap | None = None,
    *,
    field_positions: Sequence[tuple[float, float]] | None = None,
    z_nm: Sequence[float] = (-2000.0, -1000.0, 0.0, 1000.0, 2000.0),
    z_range_nm: float = 3000.0,
    diameter_nm: float = 0.0,
):
    """Matplotlib figure: for each field position (x, y in full-field pixels; default the centre,
    an edge and a corner) an x–z section through the emitter over ±``z_range_nm`` and x–y images
    at the defocus values ``z_nm``. Intensities are shown on a square-root scale."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    optics = optics or Optics()
    aberrations = aberrations or AberrationMap.default()
    rows, cols = aberrations.field_shape
    if field_positions is None:
        field_positions = [
            ((cols - 1) / 2, (rows - 1) / 2),
            (cols - 1 - cols / 16, (rows - 1) / 2),
            (cols / 16, rows / 16),
        ]
    planes = np.asarray(z_nm, dtype=np.float64)
    sweep = np.linspace(-z_range_nm, z_range_nm, 121)
    size = patch_size_px(optics, z_range_nm, diameter_nm)
    pixel = optics.pixel_size_nm
    extent_um = size * pixel / 1000.0
    fig, axes = plt.subplots(
        len(field_positions),
        1 + planes.size,
        figsize=(2.0 * (1 + planes.size) + 1.0, 2.3 * len(field_positions)),
        gridspec_kw={"width_ratios": [1.6] + [1.0] * planes.size},
        squeeze=False,
    )
    for r, (fx, fy) in enumerate(field_positions):
        coeffs = aberrations.zernike_at(fx, fy)
        section = optics.psf(sweep, zernike_nm=coeffs, shape=(size, size))
        images = optics.psf(planes, zernike_nm=coeffs, shape=(size, size))
        xz = section[:, size // 2, :]
        ax = axes[r, 0]
        ax.imshow(
            np.sqrt(xz / xz.max()),
            origin="lower",
            aspect="auto",
            cmap="magma",
            extent=(-extent_um / 2, extent_um / 2, sweep[0] / 1000, sweep[-1] / 1000),
        )
        ax.set_ylabel("defocus z (µm)")
        ax.set_title(f"x–z at field ({fx:.0f}, {fy:.0f}) px", fontsize=8)
        if r == len(field_positions) - 1:
            ax.set_xlabel("x (µm)")
        peak = images.max()
        for c, (z, image) in enumerate(zip(planes, images, strict=True)):
            ax = axes[r, c + 1]
            ax.imshow(
                np.sqrt(np.clip(image, 0, None) / peak),
                cmap="magma",
                vmin=0,
                vmax=1,
                extent=(-extent_um / 2, extent_um / 2, extent_um / 2, -extent_um / 2),
            )
            ax.set_title(f"x–y, z = {z / 1000:+.1f} µm", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    kind = "point emitter" if diameter_nm == 0 else f"{diameter_nm:.0f} nm particle"
    fig.suptitle(
        f"Simulated PSF ({kind}): NA {optics.na}, λ {optics.wavelength_nm:.0f} nm, "
        f"pixel {pixel:.0f} nm; x right, y down",
        fontsize=9,
    )
    fig.tight_layout()
    return fig


def save_psf_gallery(path: str | os.PathLike, **kwargs) -> None:
    """Write :func:`psf_gallery` to a PNG file atomically."""
    import matplotlib.pyplot as plt

    fig = psf_gallery(**kwargs)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
    finally:
        plt.close(fig)

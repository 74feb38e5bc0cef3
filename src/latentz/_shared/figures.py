"""Figure helpers shared by every stage: PNG bytes, atomic PNG files, and empty panels that say
why."""

from __future__ import annotations

import io
import os
from pathlib import Path

from latentz._shared.atomic import write_bytes_atomic

__all__ = ["figure_png", "image_png", "mark_empty", "save_figure"]


def _png(fig, dpi: int) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    return buffer.getvalue()


def figure_png(fig, *, dpi: int = 110) -> bytes:
    """Render a matplotlib figure to PNG bytes and close it."""
    import matplotlib.pyplot as plt

    png = _png(fig, dpi)
    plt.close(fig)
    return png


def image_png(rgb) -> bytes:
    """An RGB image array (rows x columns x 3, uint8) as PNG bytes, pixel for pixel."""
    import matplotlib.image

    buffer = io.BytesIO()
    matplotlib.image.imsave(buffer, rgb, format="png")
    return buffer.getvalue()


def mark_empty(ax, text: str) -> None:
    """Say in words why a panel has no data, instead of leaving an empty axis."""
    ax.cla()
    ax.set(xticks=[], yticks=[])
    ax.text(
        0.5,
        0.5,
        text,
        ha="center",
        va="center",
        wrap=True,
        fontsize=9,
        color="0.3",
        transform=ax.transAxes,
    )


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 110) -> Path:
    """Save a matplotlib figure as a PNG file atomically (the figure stays open)."""
    target = Path(path)
    write_bytes_atomic(target, _png(fig, dpi))
    return target

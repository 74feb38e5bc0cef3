"""One self-contained HTML report: figures embedded as PNG data URIs, tables as HTML.

The page loads nothing from the network, so it opens anywhere; every figure is also written as a
PNG beside it for use in papers and slides.
"""

from __future__ import annotations

import base64
import html
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.atomic import write_bytes_atomic, write_text_atomic

__all__ = ["Section", "table_html", "write_report"]


@dataclass(frozen=True)
class Section:
    """A titled part of a report: paragraphs (separated by blank lines), named figures (PNG
    bytes) with optional captions (what is shown and how to read it), and named tables."""

    title: str
    text: str = ""
    figures: dict[str, bytes] = field(default_factory=dict)
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    captions: dict[str, str] = field(default_factory=dict)


_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { border-bottom: 2px solid #444; } h2 { margin-top: 2em; border-bottom: 1px solid #bbb; }
figure { display: block; margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; }
nav a { margin-right: 1em; }
"""


def _slug(text: str) -> str:
    """An ASCII anchor and file name: letters and digits, single hyphens between words."""
    words = "".join(c if c.isascii() and c.isalnum() else " " for c in text.lower()).split()
    return "-".join(words) or "section"


def _unique(slugs: list[str]) -> list[str]:
    """The slugs, with ``-2``, ``-3`` … appended to repeats so every anchor is distinct."""
    seen: dict[str, int] = {}
    out = []
    for slug in slugs:
        seen[slug] = seen.get(slug, 0) + 1
        out.append(slug if seen[slug] == 1 else f"{slug}-{seen[slug]}")
    return out


def _decimals(values: pd.Series) -> int:
    """Decimals that show a column's typical magnitude to three significant digits (0–6)."""
    finite = values[np.isfinite(values) & (values != 0)].abs()
    if finite.empty:
        return 0
    return int(np.clip(2 - np.floor(np.log10(finite.median())), 0, 6))


def _significant(v: float) -> str:
    """Three significant digits, without exponents below 10⁵."""
    return f"{v:.0f}" if 1e3 <= abs(v) < 1e5 else f"{v:.3g}"


def table_html(table: pd.DataFrame) -> str:
    """A table as HTML: one number format per column (no "2020" beside "27.98"), or three
    significant digits per cell where a ``unit`` column says the rows differ in unit; integers
    as integers, and an em dash for a missing value."""
    floats = [c for c in table.columns if pd.api.types.is_float_dtype(table[c])]
    if "unit" in table.columns:
        formats = dict.fromkeys(floats, _significant)
    else:
        formats = {c: (lambda d: lambda v: f"{v:.{d}f}")(_decimals(table[c])) for c in floats}
    return table.to_html(index=False, formatters=formats, na_rep="—")


def write_report(
    sections: list[Section],
    path: str | os.PathLike,
    *,
    title: str = "latentz report",
    png_dir: str | os.PathLike | None = None,
) -> Path:
    """Write the sections as one self-contained HTML file (atomically); return its path.

    With ``png_dir``, every figure is also written there as ``<section>-<figure>.png``.
    """
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1><nav>",
    ]
    anchors = _unique([_slug(s.title) for s in sections])
    parts += [
        f"<a href='#{a}'>{html.escape(s.title)}</a>" for a, s in zip(anchors, sections, strict=True)
    ]
    parts.append("</nav>")
    for anchor, section in zip(anchors, sections, strict=True):
        parts.append(f"<h2 id='{anchor}'>{html.escape(section.title)}</h2>")
        if section.text:
            parts += [f"<p>{html.escape(p)}</p>" for p in section.text.split("\n\n")]
        for name, table in section.tables.items():
            parts.append(f"<h3>{html.escape(name)}</h3>")
            parts.append(table_html(table))
        for name, png in section.figures.items():
            data = base64.b64encode(png).decode("ascii")
            parts.append(
                f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,{data}'>"
                f"<figcaption><b>{html.escape(name)}.</b> "
                f"{html.escape(section.captions.get(name, ''))}</figcaption></figure>"
            )
            if png_dir is not None:
                write_bytes_atomic(Path(png_dir) / f"{anchor}-{_slug(name)}.png", png)
    parts.append("</body></html>")
    target = Path(path)
    write_text_atomic(target, "\n".join(parts))
    return target

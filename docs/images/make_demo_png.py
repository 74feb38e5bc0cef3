"""Remake docs/images/demo.png, the README's figure, from the quick demo.

    python docs/images/make_demo_png.py [--demo-dir DIR]

Runs ``latentz demo --quick --out DIR`` unless DIR already holds the demo's figures, then
shrinks the report's PSF gallery (a point emitter's image through focus at three places in the
simulated microscope's field) to ``WIDTH`` pixels and writes it beside this script.
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
from pathlib import Path

from PIL import Image

from latentz._shared.atomic import write_bytes_atomic

HERE = Path(__file__).resolve().parent
FIGURE = "simulated-microscope-psf-gallery.png"
WIDTH = 900  # px: sharp on a README page
COLOURS = 256  # a palette PNG of about 120 kB


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo-dir", type=Path, default=Path("demo-quick"))
    args = parser.parse_args()
    source = args.demo_dir / "figures" / FIGURE
    if not source.exists():
        demo = [sys.executable, "-m", "latentz.cli", "demo", "--quick", "--out", str(args.demo_dir)]
        subprocess.run(demo, check=True)
    image = Image.open(source).convert("RGB")
    height = round(image.height * WIDTH / image.width)
    buffer = io.BytesIO()
    small = image.resize((WIDTH, height), Image.LANCZOS).quantize(COLOURS)
    small.save(buffer, format="PNG", optimize=True)
    write_bytes_atomic(HERE / "demo.png", buffer.getvalue())
    print(f"wrote {HERE / 'demo.png'} ({len(buffer.getvalue()) // 1024} kB) from {source}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Open an HTML page in headless Chromium, when the machine has it, and count the images that
decoded: what a person opening the report in a browser would see, with no network."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

_PROBE = (
    "<script>window.addEventListener('load', () => {"
    " const all = Array.from(document.images);"
    " const ok = all.filter(i => i.complete && i.naturalWidth > 0).length;"
    " document.title = 'images ' + ok + ' of ' + all.length; });</script>"
)
_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--virtual-time-budget=10000",
)


def chromium() -> str | None:
    """Path of a Chromium binary, or None."""
    return next((p for name in ("chromium", "chromium-browser") if (p := shutil.which(name))), None)


def images_loaded(page: Path, work: Path) -> tuple[int, int]:
    """(images that decoded, images) when ``page`` is opened in headless Chromium.

    A copy of the page gets a script that writes the count into its title once loaded.
    """
    probe = work / "probe.html"
    probe.write_text(page.read_text().replace("</body>", _PROBE + "</body>"))
    result = subprocess.run(
        [chromium(), *_FLAGS, f"--user-data-dir={work / 'profile'}", "--dump-dom", probe.as_uri()],
        capture_output=True,
        text=True,
        timeout=180,
    )
    found = re.search(r"<title>images (\d+) of (\d+)</title>", result.stdout)
    assert found, result.stderr[-2000:]
    return int(found.group(1)), int(found.group(2))

"""Timing rounds for the benchmark scripts: run a step several times, report the median and the
range over the rounds, and write a markdown results file in ``benchmarks/results/`` that says how
it was made and how loaded the machine was.

Not a benchmark itself (``run_all.py`` runs ``bench_*.py`` only).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def time_rounds(step: Callable[[], object], rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and CPU seconds of each of ``rounds`` calls of ``step`` (warm-up, if any, is
    the caller's). CPU time, all threads of this process, shows what a loaded machine took away."""
    wall, cpu = np.empty(rounds), np.empty(rounds)
    for k in range(rounds):
        start, cpu_start = time.perf_counter(), time.process_time()
        step()
        wall[k], cpu[k] = time.perf_counter() - start, time.process_time() - cpu_start
    return wall, cpu


def spread(values: np.ndarray, digits: int = 1) -> str:
    """ "median (min–max)" of ``values`` over the rounds."""
    v = np.asarray(values, dtype=float)
    return f"{np.median(v):.{digits}f} ({v.min():.{digits}f}–{v.max():.{digits}f})"


def machine() -> str:
    """One line on the machine and its load now (call it when the benchmark starts)."""
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{platform.node()}: {os.cpu_count()} cores, load average {load} at the start; "
        f"Python {platform.python_version()}; "
        f"{datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}"
    )


def write_results(
    filename: str, title: str, started: str, notes: str, table_md: str, *, quick: bool = False
) -> Path:
    """Write ``filename`` (markdown) in ``results/``, with ``_quick`` before its suffix for a
    quick check, which never replaces the full results: the title, the exact command,
    ``started`` (the :func:`machine` line taken when the benchmark began), the notes and the
    table (markdown); atomically (a temporary file renamed over the old results)."""
    command = "python benchmarks/" + " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
    text = "\n".join([f"# {title}", "", f"`{command}`", "", started, "", notes, "", table_md, ""])
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / filename
    if quick:
        path = path.with_name(f"{path.stem}_quick{path.suffix}")
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    print(f"wrote {path}")
    return path

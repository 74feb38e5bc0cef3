"""The loop shared by the benchmarks over random family microscopes: one row per draw, written
after each draw so that a long run leaves its rows behind."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

from latentz.validation.family import FAMILY_SIZES


def run_draws(
    description: str,
    row_of: Callable[[int, str, Path | None], dict],
    write: Callable[[list[dict], argparse.Namespace, float], None],
    *,
    out: Path,
    draws: int,
    first: int,
    size: str,
    flags: dict[str, str] | None = None,
) -> None:
    """Parse ``--first/--draws/--size/--out`` (defaults as given), ``--renders/--jobs`` and the
    switches ``flags`` ({name: help}, each passed to ``row_of`` as a keyword of that name), then
    for each seed compute ``row_of(seed, size, renders)`` (``--jobs`` draws at a time, each in
    its own process), print it and ``write`` every row so far, by seed, with the seconds
    spent."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--draws", type=int, default=draws)
    parser.add_argument("--first", type=int, default=first, help="seed of the first draw")
    parser.add_argument("--size", default=size, choices=tuple(FAMILY_SIZES))
    parser.add_argument("--out", type=Path, default=out)
    parser.add_argument(
        "--renders",
        type=Path,
        default=None,
        help="a folder that keeps each draw's images for later runs",
    )
    parser.add_argument("--jobs", type=int, default=1, help="draws run at once")
    for name, text in (flags or {}).items():
        parser.add_argument(f"--{name.replace('_', '-')}", action="store_true", help=text)
    args = parser.parse_args()
    switches = {name: getattr(args, name) for name in flags or {}}
    warnings.simplefilter("ignore")
    start, rows = time.perf_counter(), []
    seeds = range(args.first, args.first + args.draws)
    pool = ProcessPoolExecutor(args.jobs, get_context("spawn"), warnings.simplefilter, ("ignore",))
    with pool:
        pending = [pool.submit(row_of, seed, args.size, args.renders, **switches)
                   for seed in seeds]  # fmt: skip
        for done in as_completed(pending):
            rows = sorted([*rows, done.result()], key=lambda row: row["seed"])
            print(done.result(), file=sys.stderr, flush=True)
            write(rows, args, time.perf_counter() - start)

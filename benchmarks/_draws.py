"""The loop shared by the benchmarks over random family microscopes: one row per draw, written
after each draw so that a long run leaves its rows behind."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

from latentz.validation.family import FAMILY_SIZES


def run_draws(
    description: str,
    row_of: Callable[[int, str], dict],
    write: Callable[[list[dict], argparse.Namespace, float], None],
    *,
    out: Path,
    draws: int,
    first: int,
    size: str,
) -> None:
    """Parse ``--first/--draws/--size/--out`` (defaults as given), then for each seed compute
    ``row_of(seed, size)``, print it and ``write`` every row so far with the seconds spent."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--draws", type=int, default=draws)
    parser.add_argument("--first", type=int, default=first, help="seed of the first draw")
    parser.add_argument("--size", default=size, choices=tuple(FAMILY_SIZES))
    parser.add_argument("--out", type=Path, default=out)
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    start, rows = time.perf_counter(), []
    for seed in range(args.first, args.first + args.draws):
        rows.append(row_of(seed, args.size))
        print(rows[-1], file=sys.stderr, flush=True)
        write(rows, args, time.perf_counter() - start)

"""Run every benchmark in this folder, one after another, in this Python environment.

    python benchmarks/run_all.py [--skip NAME ...]

Each benchmark prints its own table and writes its results under benchmarks/ (results*.md or
results/). Benchmarks that compare with Picasso need `pip install -r benchmarks/requirements.txt`;
the comparison on the SMLM 2016 bead stack needs ../shared/data beside the repository.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip", nargs="*", default=[], help="benchmark names to skip")
    args = parser.parse_args()
    scripts = sorted(HERE.glob("bench_*.py")) + sorted(HERE.glob("compare_*.py"))
    failed = []
    for script in scripts:
        if script.stem in args.skip:
            continue
        print(f"\n=== {script.stem}", flush=True)
        start = time.perf_counter()
        code = subprocess.call([sys.executable, str(script)])
        print(f"=== {script.stem}: exit {code}, {time.perf_counter() - start:.0f} s", flush=True)
        if code:
            failed.append(script.stem)
    if failed:
        print(f"\nFailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""What the honest uncertainties cost: the sandwich covariance in ``fit_arrays`` and the
brightness correction (:mod:`latentz.calibration.dimming`) in ``Calibration.apply``.

``python benchmarks/bench_errors.py [--n 20000] [--out benchmarks/results/bench_errors.md]``
(``NUMBA_NUM_THREADS=1`` before it for one thread: CPU time per row then holds no thread waiting
for another)

- **fit**: ``fit_arrays`` (MLE, CPU) on ``--n`` simulated 11 x 11 and 15 x 15 ROIs of eq. 1
  (10³–10⁴ photons, background 10–100 per px) with its default Cramér–Rao errors and with
  ``errors="sandwich"``, against the sandwich covariance alone
  (:func:`latentz.fit.robust.sandwich_batch`, which ``errors="sandwich"`` and ``localize`` run
  after the fit);
- **apply**: ``Calibration.apply`` on the spots of the small validation study (repeated to
  ``--n`` rows), with and without the calibration's refits as dimmer emitters (without them
  ``apply`` skips the correction, as for a calibration saved before it existed).

Best of ``--rounds`` runs each, in wall-clock and in CPU seconds of all threads (what a loaded
machine leaves: compare CPU times there). The file written with ``--out`` starts with the command
and the machine's load.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _rounds import machine, time_rounds  # noqa: E402


def best_of(rounds: int, run, *args, **kwargs) -> tuple[float, float]:
    """Shortest wall and CPU seconds of ``rounds`` calls of ``run(*args, **kwargs)``."""
    wall, cpu = time_rounds(lambda: run(*args, **kwargs), rounds)
    return float(wall.min()), float(cpu.min())


def _row(step: str, n: int, times: tuple[float, float], of: tuple[float, float] | None = None):
    """One table row: wall and CPU seconds, µs per row of each, and the CPU share of ``of``."""
    (wall, cpu), row = times, {"step": step, "n": n}
    row |= {"wall_s": wall, "cpu_s": cpu, "us_per_row": 1e6 * wall / n,
            "cpu_us_per_row": 1e6 * cpu / n}  # fmt: skip
    if of is not None:
        row["cpu_share"] = cpu / of[1]
    return row


def fit_rows(n: int, rounds: int) -> list[dict]:
    from latentz.fit import fit_arrays, render_rois
    from latentz.fit.robust import sandwich_batch

    rng = np.random.default_rng(0)
    rows = []
    for size in (11, 15):
        photons = 10 ** rng.uniform(3, 4, n)
        wx, wy = rng.uniform(1.0, 2.0, n), rng.uniform(1.0, 2.0, n)
        truth = {"x": size / 2 - 0.5 + rng.uniform(-0.5, 0.5, n),
                 "y": size / 2 - 0.5 + rng.uniform(-0.5, 0.5, n),
                 "amplitude": photons / (2 * np.pi * wx * wy),
                 "background": rng.uniform(10, 100, n),
                 "wx": wx, "wy": wy, "rho": rng.uniform(-0.5, 0.5, n)}  # fmt: skip
        rois = rng.poisson(render_rois(truth, shape=size)).astype(np.float64)
        fit_arrays(rois[:100], device="cpu", errors="sandwich")  # compile
        bound = best_of(rounds, fit_arrays, rois, device="cpu")
        whole = best_of(rounds, fit_arrays, rois, device="cpu", errors="sandwich")
        params = fit_arrays(rois, device="cpu").params
        sandwich = best_of(rounds, sandwich_batch, rois, params, 0.0)
        rows.append(_row(f"fit_arrays {size}x{size}, Cramér–Rao errors", n, bound))
        rows.append(_row(f"fit_arrays {size}x{size}, errors='sandwich'", n, whole))
        rows.append(_row(f"  of which sandwich {size}x{size}", n, sandwich, whole))
    return rows


def apply_rows(n: int, rounds: int) -> list[dict]:
    from latentz import calibrate
    from latentz.calibration.dimming import DIM_COLUMNS
    from latentz.validation import make_data
    from latentz.validation.truth import localize_test

    data = make_data("small", seed=1, n_frames=16)
    cal = calibrate(data.stacks, data.z_nm, camera=data.camera, shape="rho_w", roi_size=15,
                    field_model="zernike")  # fmt: skip
    spots = localize_test(data, roi_size=15)
    spots = pd.concat([spots] * int(np.ceil(n / len(spots))), ignore_index=True).iloc[:n]
    spots.attrs = {"roi_size": 15}
    cal.apply(spots)  # models and cross-validation built once
    plain = replace(cal, traces=_without(cal.traces, DIM_COLUMNS))
    plain._cache.update({k: v for k, v in cal._cache.items()})
    with_dim = best_of(rounds, cal.apply, spots)
    without = best_of(rounds, plain.apply, spots)
    return [_row("apply without the brightness correction", n, without),
            _row("apply with it", n, with_dim, without)]  # fmt: skip


def _without(traces, names):
    from latentz.calibration.traces import Traces

    data = {k: v for k, v in traces.data.items() if k not in names}
    return Traces(traces.z_nm, data, stack=traces.stack, crowded=traces.crowded,
                  offset_px=traces.offset_px)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20_000, help="ROIs / spots per timing")
    parser.add_argument("--rounds", type=int, default=3, help="timed runs (best of)")
    parser.add_argument("--out", help="also write the Markdown table here (atomically)")
    args = parser.parse_args()
    started = machine()
    table = pd.DataFrame(fit_rows(args.n, args.rounds) + apply_rows(args.n, args.rounds))
    threads = os.environ.get("NUMBA_NUM_THREADS", "all")
    command = " ".join(["python benchmarks/bench_errors.py", *sys.argv[1:]])
    text = "\n\n".join([f"`{command}`, {threads} numba thread(s)", started,
                         table.to_markdown(index=False, floatfmt=".3g")])  # fmt: skip
    print(text)
    if args.out:
        folder = os.path.dirname(os.path.abspath(args.out))
        with tempfile.NamedTemporaryFile("w", dir=folder, delete=False, suffix=".tmp") as f:
            f.write(text + "\n")
        os.replace(f.name, args.out)


if __name__ == "__main__":
    main()

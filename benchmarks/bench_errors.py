"""What the honest uncertainties cost: the sandwich covariance in ``fit_arrays`` and the
brightness correction (:mod:`latentz.calibration.dimming`) in ``Calibration.apply``.

``python benchmarks/bench_errors.py [--n 20000] [--out benchmarks/results/bench_errors.md]``

- **fit**: ``fit_arrays`` (MLE, CPU) on ``--n`` simulated 11 x 11 and 15 x 15 ROIs of eq. 1
  (10³–10⁴ photons, background 10–100 per px), against the sandwich covariance alone
  (:func:`latentz.fit.robust.sandwich_batch`, which ``fit_arrays`` now runs after the fit);
- **apply**: ``Calibration.apply`` on the spots of the small validation study (repeated to
  ``--n`` rows), with and without the calibration's refits as dimmer emitters (without them
  ``apply`` skips the correction, as for a calibration saved before it existed).

Best of ``--rounds`` runs each (the machine may be shared).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace

import numpy as np
import pandas as pd


def best_of(rounds: int, run, *args, **kwargs) -> float:
    """Shortest wall time (s) of ``rounds`` calls of ``run(*args, **kwargs)``."""
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        run(*args, **kwargs)
        times.append(time.perf_counter() - start)
    return min(times)


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
        fit = fit_arrays(rois[:100], device="cpu")  # compile
        sandwich_batch(rois[:100], fit.params, 0.0)
        whole = best_of(rounds, fit_arrays, rois, device="cpu")
        params = fit_arrays(rois, device="cpu").params
        sandwich = best_of(rounds, sandwich_batch, rois, params, 0.0)
        rows.append({"step": f"fit_arrays {size}x{size} (with sandwich)", "n": n,
                     "time_s": whole, "us_per_row": 1e6 * whole / n})  # fmt: skip
        rows.append({"step": f"  of which sandwich {size}x{size}", "n": n, "time_s": sandwich,
                     "us_per_row": 1e6 * sandwich / n, "share": sandwich / whole})  # fmt: skip
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
    return [
        {"step": "apply without the brightness correction", "n": n, "time_s": without,
         "us_per_row": 1e6 * without / n},
        {"step": "apply with it", "n": n, "time_s": with_dim, "us_per_row": 1e6 * with_dim / n,
         "share": with_dim / without},
    ]  # fmt: skip


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
    table = pd.DataFrame(fit_rows(args.n, args.rounds) + apply_rows(args.n, args.rounds))
    text = table.to_markdown(index=False, floatfmt=".3g")
    print(text)
    if args.out:
        folder = os.path.dirname(os.path.abspath(args.out))
        with tempfile.NamedTemporaryFile("w", dir=folder, delete=False, suffix=".tmp") as f:
            f.write(text + "\n")
        os.replace(f.name, args.out)


if __name__ == "__main__":
    main()

"""Speed and precision of latentz's eq. 1 fits against Picasso and SciPy, on the same ROIs.

Run it in the benchmark environment (``benchmarks/requirements.txt``; Picasso is never a
dependency of latentz)::

    python -m venv /tmp/benchenv --system-site-packages
    /tmp/benchenv/bin/pip install -r benchmarks/requirements.txt
    /tmp/benchenv/bin/python benchmarks/bench_fit.py --out benchmarks/results/bench_fit.md

For 7 x 7 and 11 x 11 ROIs it simulates ``--n`` ROIs of eq. 1 with Poisson noise (sub-pixel
positions, rho in [-0.6, 0.6], 10^3–10^5 photons, background 10–100 photons/px; widths in
[1, 1.5] px for 7 x 7 and [1, 2] px for 11 x 11, so that neither ROI cuts the spot at less than
two standard deviations) and fits them with, on ``--threads`` threads each (default 2; 1 compares
the per-fit work without the threads' scheduling):

- latentz ``fit_arrays`` (``mle`` and ``wlsq``): numba, parallel over ROIs;
- Picasso ``picasso.fitting.gaussfit.fit_spots_async`` (``ROTATED`` model, ``mle=True``,
  ``n_threads``) seeded by ``picasso.fitting.seeds.initial_parameters_gauss(..., rotated=True)``,
  with its default convergence schedule; the rotated Gaussian spans the same family as eq. 1, so
  the same Cramér–Rao bounds apply to its x and y;
- the older ``picasso.gaussmle.gaussmle`` (``sigmaxy``, eps 1e-3, 100 iterations), run on the
  same threads over equal parts of the ROIs (``gaussmle_async`` would take 75 % of the cores).
  It integrates an unrotated Gaussian over each pixel, so it does not model these ROIs;
- ``scipy.optimize.least_squares`` (``method="lm"``, analytic Jacobian of eq. 1) one ROI at a
  time in Python, on the first ``--n-scipy`` ROIs.

Timings are the best of ``--rounds`` rounds on the first ``--n-time`` ROIs, the methods taking turns
in a random order each round (the machine is shared, so the best of many short runs is the stable
statistic); they include each method's own start / seeds. ``vs_picasso_per_round`` is the speed
ratio to Picasso's ROTATED MLE within each round: median (min-max over the rounds).
Precision, from one run over all ``--n`` ROIs: the standard deviation of error / Cramér–Rao
bound for x and y, its robust twin (1.4826 x MAD), and the fraction of gross failures
(|error| > 5 bounds in x or y, or no finite result).
"""

from __future__ import annotations

import argparse
import time
import warnings
from concurrent import futures

import numpy as np
import pandas as pd

from latentz.fit import PARAMS, amplitude_of, crlb, fit_arrays, moment_start, render_rois
from latentz.fit._model import model_and_jacobian

WIDTHS = {7: (1.0, 1.5), 11: (1.0, 2.0)}


def simulate(n: int, size: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Truth (n, 7) in `PARAMS` order and Poisson ROIs (n, size, size) in photoelectrons."""
    rng = np.random.default_rng(seed)
    c = (size - 1) / 2
    lo, hi = WIDTHS[size]
    table = pd.DataFrame(
        {
            "x": c + rng.uniform(-0.5, 0.5, n),
            "y": c + rng.uniform(-0.5, 0.5, n),
            "photons": 10 ** rng.uniform(3, 5, n),
            "background": rng.uniform(10, 100, n),
            "wx": rng.uniform(lo, hi, n),
            "wy": rng.uniform(lo, hi, n),
            "rho": rng.uniform(-0.6, 0.6, n),
        }
    )
    table["amplitude"] = amplitude_of(table.photons, table.wx, table.wy, table.rho)
    truth = table[list(PARAMS)].to_numpy()
    rois = rng.poisson(render_rois(truth, shape=size)).astype(np.float64)
    return truth, rois


def run_latentz(rois: np.ndarray, method: str) -> np.ndarray:
    result = fit_arrays(rois, method=method)
    return result.params[:, :2]


def run_picasso_rotated(rois: np.ndarray, threads: int) -> np.ndarray:
    from picasso.fitting import gaussfit, seeds

    spots = rois.astype(np.float32)
    init = seeds.initial_parameters_gauss(spots, spots.shape[1], rotated=True)
    job = gaussfit.fit_spots_async(gaussfit.ROTATED, spots, init, mle=True, n_threads=threads)
    while not job.finished():
        time.sleep(0.0005)
    job.raise_errors()
    theta = job.results()[0]
    return np.column_stack([theta[:, 1], theta[:, 2]])


def run_gaussmle(rois: np.ndarray, threads: int) -> np.ndarray:
    from picasso import gaussmle

    spots = rois.astype(np.float32)
    parts = np.array_split(np.arange(len(spots)), threads)
    with warnings.catch_warnings(), futures.ThreadPoolExecutor(threads) as pool:
        warnings.simplefilter("ignore")
        fits = list(pool.map(lambda idx: gaussmle._gaussmle(spots[idx], 1e-3, 100), parts))
    theta = np.concatenate([f[0] for f in fits])
    return theta[:, :2].astype(np.float64)


def run_scipy(rois: np.ndarray) -> np.ndarray:
    from scipy.optimize import least_squares

    n, h, w = rois.shape
    starts = moment_start(rois)
    out = np.full((n, 2), np.nan)

    def natural(p):
        return np.array([[*p[:4], np.exp(p[4]), np.exp(p[5]), np.tanh(p[6])]])

    for k in range(n):
        data = rois[k].ravel()
        s = starts[k]
        p0 = np.array([*s[:4], np.log(s[4]), np.log(s[5]), np.arctanh(s[6])])

        def residual(p, data=data):
            return model_and_jacobian(natural(p), (h, w), jacobian=False)[0][0] - data

        def jacobian(p):
            return model_and_jacobian(natural(p), (h, w))[1][0]

        try:
            fit = least_squares(residual, p0, jac=jacobian, method="lm")
            out[k] = fit.x[:2]
        except (ValueError, np.linalg.LinAlgError):
            continue
    return out


def precision(xy: np.ndarray, truth: np.ndarray, bound: np.ndarray) -> dict[str, float]:
    z = (xy - truth[:, :2]) / bound[:, :2]
    finite = np.all(np.isfinite(z), axis=1)
    gross = ~finite | np.any(np.abs(np.where(np.isfinite(z), z, np.inf)) > 5, axis=1)
    zf = z[finite]
    mad = 1.4826 * np.median(np.abs(zf - np.median(zf, axis=0)), axis=0)
    return {
        "std_x": float(zf[:, 0].std()),
        "std_y": float(zf[:, 1].std()),
        "robust_x": float(mad[0]),
        "robust_y": float(mad[1]),
        "gross": float(gross.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=100_000, help="ROIs per size (precision)")
    parser.add_argument("--n-time", type=int, default=20_000, help="ROIs per timed run")
    parser.add_argument("--n-scipy", type=int, default=2_000, help="ROIs for the SciPy loop")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved timing rounds")
    parser.add_argument("--threads", type=int, default=2, help="threads per method")
    parser.add_argument("--out", help="also write the Markdown table here (atomically)")
    args = parser.parse_args()

    import numba

    numba.set_num_threads(args.threads)
    methods = {
        "latentz mle": lambda r: run_latentz(r, "mle"),
        "latentz wlsq": lambda r: run_latentz(r, "wlsq"),
        "Picasso gaussfit ROTATED mle": lambda r: run_picasso_rotated(r, args.threads),
        "Picasso gaussmle (old)": lambda r: run_gaussmle(r, args.threads),
        "scipy least_squares": run_scipy,
    }
    rows = []
    for size in (7, 11):
        truth, rois = simulate(args.n, size, seed=size)
        bound = crlb(truth, shape=size)
        for run in methods.values():  # compile / warm up
            run(rois[:50])
        results = {  # precision over all ROIs (untimed)
            name: run(rois[: args.n_scipy if name.startswith("scipy") else args.n])
            for name, run in methods.items()
        }
        best = dict.fromkeys(methods, np.inf)
        per_round = {name: [] for name in methods}
        order = list(methods)
        rng = np.random.default_rng(0)
        for _ in range(args.rounds):  # speed: best of interleaved rounds, in random order
            rng.shuffle(order)
            for name in order:
                n = min(args.n_scipy if name.startswith("scipy") else args.n_time, args.n)
                t0 = time.perf_counter()
                methods[name](rois[:n])
                per_round[name].append((time.perf_counter() - t0) / n)
                best[name] = min(best[name], per_round[name][-1])
        picasso = np.array(per_round["Picasso gaussfit ROTATED mle"])
        for name in methods:
            n = len(results[name])
            stats = precision(results[name], truth[:n], bound[:n])
            # the ratio to Picasso within each round (same machine state), over the rounds
            ratio = picasso / np.array(per_round[name])
            spread = f"{np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f})"
            rows.append({"roi": f"{size}x{size}", "method": name, "n": n,
                         "fits_per_s": 1.0 / best[name],
                         "vs_picasso_per_round": spread, **stats})  # fmt: skip
    table = pd.DataFrame(rows)
    for size in ("7x7", "11x11"):
        sel = table.roi == size
        ref = table[sel & (table.method == "Picasso gaussfit ROTATED mle")].fits_per_s.iloc[0]
        table.loc[sel, "speed_vs_picasso"] = table[sel].fits_per_s / ref
    text = table.to_markdown(index=False, floatfmt=".4g")
    print(text)
    if args.out:
        from latentz._shared.atomic import write_text_atomic

        write_text_atomic(args.out, text + "\n")


if __name__ == "__main__":
    main()

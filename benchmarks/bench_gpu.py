"""GPU engine benchmark (issue 15): eq.-1 fits/s against Picasso's GPU fitter, full-frame localize.

1. Fits: the same ROIs (eq. 1 rendered at pixel centres with Poisson noise, never shown to either
   fitter's model) are fitted in the same run by latentz (``fit_arrays(method="mle",
   device="cuda")``, moment start computed on the GPU) and by Picasso 0.11.3's GPU fitter
   (``picasso.fitting.gaussfit_cuda.fit_spots``, ROTATED model, Poisson MLE, seeds from
   ``picasso.fitting.seeds.initial_parameters_gauss``, not timed), at 7 x 7 and 11 x 11 px. Both
   timings include the host-device transfers; each fitter is warmed up (compiled) first and the
   best of ``--repeats`` runs counts. Accuracy: the spread of x - x_true over the Cramér–Rao bound
   at the truth (:func:`latentz.fit.crlb`, on a subsample), and the converged fraction.
2. Full frames: ``localize`` of 2048 x 2048 uint16 frames (camera model, detection, fits, ROI
   re-centring) with ``device="cuda"``, in frames/s: the first run and the best of two more.
3. The devices agree: the same ROIs fitted on the CPU and the GPU (converged flags, largest x, y
   difference), and the same frames localized on both (spots found, largest x, y difference).
4. Sparse against dense frames: ``localize`` on the GPU and on every CPU core, best of two, with
   tens and with a thousand emitters per frame, to say when ``device="cpu"`` is the faster.

Ratios are printed to Picasso's fits/s and to the paper's 90.9 Hz acquisition rate; the table is
also written to ``benchmarks/results/bench_gpu.md``. Needs an NVIDIA GPU and
``pip install 'latentz[gpu]' picassosr==0.11.3``; without a GPU it stops with one clear line.

    python benchmarks/bench_gpu.py [--rois 1000000] [--frames 50] [--emitters 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from latentz._shared.engine import cuda_status
from latentz.camera import Camera
from latentz.fit import amplitude_of, crlb, fit_arrays, render_rois

PAPER_HZ = 90.9
FRAME = 2048
CRLB_SAMPLE = 20_000
WIDTHS_PX = {7: (1.0, 1.5), 11: (1.2, 2.2)}


def emitters(n: int, size: int, rng: np.random.Generator) -> pd.DataFrame:
    """Astigmatic, tilted emitters near the ROI centre, 1e3 to 1e4 photons."""
    c = (size - 1) / 2
    table = pd.DataFrame(
        {
            "x": c + rng.uniform(-0.5, 0.5, n),
            "y": c + rng.uniform(-0.5, 0.5, n),
            "photons": np.exp(rng.uniform(np.log(1e3), np.log(1e4), n)),
            "background": rng.uniform(10.0, 50.0, n),
            "wx": rng.uniform(*WIDTHS_PX[size], n),
            "wy": rng.uniform(*WIDTHS_PX[size], n),
            "rho": rng.uniform(-0.4, 0.4, n),
        }
    )
    table["amplitude"] = amplitude_of(table["photons"], table["wx"], table["wy"], table["rho"])
    return table


def noisy_rois(table: pd.DataFrame, size: int, rng: np.random.Generator) -> np.ndarray:
    rois = np.empty((len(table), size, size), np.float32)
    for a in range(0, len(table), 100_000):
        part = table.iloc[a : a + 100_000]
        rois[a : a + len(part)] = rng.poisson(render_rois(part, shape=size))
    return rois


def best_time(run, repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - start)
    return best, out


def spread_over_crlb(x: np.ndarray, ok: np.ndarray, table: pd.DataFrame, bound: np.ndarray):
    """std(x - x_true) / rms(CRLB_x) over the converged fits of the subsample."""
    sub = ok[:CRLB_SAMPLE]
    error = x[:CRLB_SAMPLE][sub] - table["x"].to_numpy()[:CRLB_SAMPLE][sub]
    return float(np.std(error) / np.sqrt(np.mean(bound[sub, 0] ** 2)))


def bench_fits(n: int, size: int, repeats: int, rng: np.random.Generator) -> dict:
    table = emitters(n, size, rng)
    rois = noisy_rois(table, size, rng)
    bound = crlb(table.iloc[:CRLB_SAMPLE], shape=size)
    row = {"ROI": f"{size} x {size}", "ROIs": n}
    fit_arrays(rois[:10_000], method="mle", device="cuda")  # compile
    seconds, fit = best_time(lambda: fit_arrays(rois, method="mle", device="cuda"), repeats)
    row["latentz fits/s"] = n / seconds
    row["latentz converged"] = float(fit.converged.mean())
    row["latentz iterations"] = float(fit.iterations[fit.converged].mean())
    row["latentz spread/CRLB"] = spread_over_crlb(fit.params[:, 0], fit.converged, table, bound)
    try:
        from picasso.fitting import gaussfit, gaussfit_cuda, seeds
    except ImportError as exc:
        print(f"bench_gpu: Picasso not measured ({exc}); pip install picassosr==0.11.3")
        return row
    init = seeds.initial_parameters_gauss(rois, size, rotated=True)

    def picasso_fit():
        return gaussfit_cuda.fit_spots(gaussfit.ROTATED, rois, init, mle=True)

    gaussfit_cuda.fit_spots(gaussfit.ROTATED, rois[:10_000], init[:10_000], mle=True)  # compile
    seconds, (thetas, _, states, iterations) = best_time(picasso_fit, repeats)
    ok = states == 0
    row["Picasso fits/s"] = n / seconds
    row["Picasso converged"] = float(ok.mean())
    row["Picasso iterations"] = float(iterations[ok].mean())
    row["Picasso spread/CRLB"] = spread_over_crlb(thetas[:, 1], ok, table, bound)
    row["latentz / Picasso"] = row["latentz fits/s"] / row["Picasso fits/s"]
    return row


def full_frames(n_frames: int, per_frame: int, rng: np.random.Generator) -> np.ndarray:
    """uint16 frames (offset 100 ADU, gain 1) holding ``per_frame`` emitters each."""
    size = 11
    frames = rng.poisson(20.0, (n_frames, FRAME, FRAME)).astype(np.float32)
    table = emitters(n_frames * per_frame, size, rng)
    spots = render_rois(table.assign(background=0.0), shape=size).astype(np.float32)
    t = np.repeat(np.arange(n_frames), per_frame)
    corner = rng.integers(0, FRAME - size, (len(t), 2))
    offsets = np.arange(size)
    rows = corner[:, 0, None, None] + offsets[None, :, None]
    cols = corner[:, 1, None, None] + offsets[None, None, :]
    np.add.at(frames, (t[:, None, None], rows, cols), rng.poisson(spots))
    return (frames + 100.0).astype(np.uint16)


def bench_localize(n_frames: int, per_frame: int, rng: np.random.Generator) -> dict:
    from latentz.localization import localize

    frames = full_frames(n_frames, per_frame, rng)
    camera = Camera(offset=100.0, gain=1.0, readnoise=1.5)
    localize(frames[:2], camera=camera, device="cuda")  # compile
    run = partial(localize, frames, camera=camera, device="cuda")
    first, _ = best_time(run, 1)
    seconds, spots = best_time(run, 2)
    rate = n_frames / seconds
    return {
        "frames": f"{n_frames} x {FRAME} x {FRAME}",
        "emitters/frame": per_frame,
        "spots": len(spots),
        "converged": float(spots["converged"].mean()),
        "first run, frames/s": n_frames / first,
        "frames/s": rate,
        "/ 90.9 Hz": rate / PAPER_HZ,
    }


def bench_agreement(n: int, n_frames: int, per_frame: int, rng: np.random.Generator) -> dict:
    """The same ROIs and frames on both devices: flags, spots and the largest x, y gap, px."""
    from latentz.localization import localize

    row: dict[str, object] = {}
    for size in (7, 11):
        rois = noisy_rois(emitters(n, size, rng), size, rng)
        cpu, gpu = (fit_arrays(rois, method="mle", device=d) for d in ("cpu", "cuda"))
        both = cpu.converged & gpu.converged
        shift = np.abs(cpu.params[both, :2] - gpu.params[both, :2])
        same = cpu.converged == gpu.converged
        row[f"{size} x {size}: same converged flag"] = float(same.mean())
        row[f"{size} x {size}: largest x, y difference, px"] = float(shift.max())
    frames = full_frames(n_frames, per_frame, rng)
    camera = Camera(offset=100.0, gain=1.0, readnoise=1.5)
    cpu, gpu = (localize(frames, camera=camera, device=d) for d in ("cpu", "cuda"))
    row["frames: spots CPU / GPU"] = f"{len(cpu)} / {len(gpu)}"
    if len(cpu) == len(gpu):
        key = ["frame", "y", "x"]
        a, b = (t.sort_values(key)[["x", "y"]].to_numpy() for t in (cpu, gpu))
        row["frames: largest x, y difference, px"] = float(np.abs(a - b).max())
    return row


def bench_devices(n_frames: int, rng: np.random.Generator) -> list[dict]:
    """frames/s of ``localize`` on the GPU and on the CPU, best of two, sparse and dense frames."""
    from latentz.localization import localize

    camera = Camera(offset=100.0, gain=1.0, readnoise=1.5)
    rows = []
    for per_frame in (30, 1000):
        frames = full_frames(n_frames, per_frame, rng)
        row: dict[str, object] = {"emitters/frame": per_frame, "frames": n_frames}
        for device, name in (("cuda", "GPU"), ("cpu", "CPU")):
            run = partial(localize, frames, camera=camera, device=device)
            localize(frames[:2], camera=camera, device=device)  # compile
            seconds, _ = best_time(run, 2)
            row[f"{name}, frames/s"] = n_frames / seconds
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rois", type=int, default=1_000_000, help="ROIs per size")
    parser.add_argument("--frames", type=int, default=50, help="2048 x 2048 frames to localize")
    parser.add_argument("--emitters", type=int, default=1000, help="emitters per frame")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    reason = cuda_status()
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        reason = "numba's CUDA simulator is on (NUMBA_ENABLE_CUDASIM=1)"
    if reason is not None:
        sys.exit(f"bench_gpu: error: needs an NVIDIA GPU, but {reason}.")
    rng = np.random.default_rng(15)
    fits = pd.DataFrame([bench_fits(args.rois, size, args.repeats, rng) for size in (7, 11)])
    frames = pd.DataFrame([bench_localize(args.frames, args.emitters, rng)])
    agree = pd.Series(bench_agreement(20_000, 4, args.emitters, rng))
    devices = pd.DataFrame(bench_devices(32, rng))
    from numba import cuda

    device = cuda.get_current_device().name
    device = device.decode() if isinstance(device, bytes) else device
    text = "\n\n".join(
        [
            f"# GPU engine ({device})",
            "## eq.-1 MLE fits, same ROIs, transfers included\n\n" + fits.to_markdown(index=False),
            "## Full-frame localize (device='cuda')\n\n" + frames.to_markdown(index=False),
            "## CPU and GPU on the same inputs\n\n"
            + agree.rename("value").to_frame().to_markdown(),
            f"## localize on the GPU and on {os.cpu_count()} CPU cores, best of two\n\n"
            + devices.to_markdown(index=False),
            f"Targets: fits/s >= Picasso at both sizes with spread/CRLB near 1; frames/s >= "
            f"{10 * PAPER_HZ:.0f} (10 x {PAPER_HZ} Hz).",
        ]
    )
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_gpu.md").write_text(text + "\n")


if __name__ == "__main__":
    main()

"""Run the CUDA kernels under numba's CUDA simulator and the CPU kernels on the same inputs.

Run as ``NUMBA_ENABLE_CUDASIM=1 python cuda_sim_cases.py OUT_DIR`` (test_cuda_simulator.py does):
the simulator must be switched on before ``numba.cuda`` is first imported, so it runs in a process
of its own and leaves the rest of the test session on the real CPU path. It writes
``fits.npz`` (per method, both devices and the truth), ``spots_{cpu,cuda}.parquet``,
``camera_spots_{cpu,cuda}.parquet`` (the same movie as a camera stores it, one chunk per frame)
and ``given_noise_{cpu,cuda}.npz`` (detections with a given noise level).
The simulator runs every GPU thread as Python, so the inputs are small.
"""

import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1", "run with NUMBA_ENABLE_CUDASIM=1"

import latentz.fit._cuda as fit_cuda  # noqa: E402
from latentz.camera import Camera  # noqa: E402
from latentz.detect._cuda import detect_arrays_cuda  # noqa: E402
from latentz.detect.api import band_noise, detect_arrays  # noqa: E402
from latentz.fit import amplitude_of, fit_arrays, render_rois  # noqa: E402
from latentz.localization import localize  # noqa: E402

READNOISE = 1.5
N_ROIS = 100


def truth(n: int, shape: tuple[int, int], rng: np.random.Generator) -> pd.DataFrame:
    """Emitters near the ROI centre over two decades of photons, astigmatic and tilted."""
    h, w = shape
    table = pd.DataFrame(
        {
            "x": (w - 1) / 2 + rng.uniform(-0.7, 0.7, n),
            "y": (h - 1) / 2 + rng.uniform(-0.7, 0.7, n),
            "photons": np.exp(rng.uniform(np.log(200.0), np.log(2e4), n)),
            "background": rng.uniform(2.0, 40.0, n),
            "wx": rng.uniform(0.9, 1.8, n),
            "wy": rng.uniform(0.9, 1.8, n),
            "rho": rng.uniform(-0.4, 0.4, n),
        }
    )
    table["amplitude"] = amplitude_of(table["photons"], table["wx"], table["wy"], table["rho"])
    return table


def rois_of(table: pd.DataFrame, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Poisson photoelectrons plus Gaussian read noise; then a few ROIs the fit must refuse or
    survive: one with a NaN pixel, one blank, one with the spot at the corner."""
    mean = render_rois(table, shape=shape)
    rois = rng.poisson(mean) + rng.normal(0.0, READNOISE, mean.shape)
    rois[0, 1, 1] = np.nan
    rois[1] = rng.poisson(5.0, shape)
    rois[2] = rng.poisson(render_rois(table.iloc[[2]].assign(x=0.0, y=0.0), shape=shape)[0])
    return rois


def fit_cases(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Every method on 7 x 7 ROIs (MLE on all, the others on the first 60); MLE on 9 x 11 ROIs,
    half of them from a given start."""
    out = {}
    table = truth(N_ROIS, (7, 7), rng)
    rois = rois_of(table, (7, 7), rng)
    out["truth_7x7"] = table[["x", "y"]].to_numpy()
    for method, n in (("mle", N_ROIS), ("wlsq", 60), ("lsq", 60)):
        for device in ("cpu", "cuda"):
            fit = fit_arrays(rois[:n], method=method, readnoise=READNOISE, device=device)
            for name, value in fit._asdict().items():
                out[f"{method}_7x7_{device}_{name}"] = value
    table = truth(24, (9, 11), rng)
    rois = rois_of(table, (9, 11), rng)
    init = table[["x", "y", "amplitude", "background", "wx", "wy", "rho"]].to_numpy() + 0.2
    init[::2] = np.nan  # the moment start for these
    out["truth_9x11"] = table[["x", "y"]].to_numpy()
    for device in ("cpu", "cuda"):
        fit = fit_arrays(rois, method="mle", readnoise=READNOISE, init=init, device=device)
        for name, value in fit._asdict().items():
            out[f"mle_9x11_{device}_{name}"] = value
    return out


def movie(rng: np.random.Generator) -> np.ndarray:
    """Two 24 x 32 frames: spots anywhere (one at the edge, two neighbours in frame 1)."""
    frames = np.full((2, 24, 32), 12.0)
    spots = [
        [(6.2, 7.5), (20.4, 9.1), (14.0, 17.3), (30.8, 22.6)],
        [(7.0, 8.0), (12.0, 11.0), (24.7, 15.4)],
    ]
    for t, positions in enumerate(spots):
        for x, y in positions:
            frames[t] += render_rois(
                {
                    "x": [x],
                    "y": [y],
                    "photons": [rng.uniform(800.0, 3000.0)],
                    "background": [0.0],
                    "wx": [rng.uniform(0.9, 1.4)],
                    "wy": [rng.uniform(0.9, 1.4)],
                    "rho": [rng.uniform(-0.3, 0.3)],
                },
                shape=(24, 32),
            )[0]
    return rng.poisson(frames).astype(np.float64)


def as_stored(frames: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, Camera]:
    """The movie as a camera stores it: uint16 ADU with an offset, a gain and a flatfield."""
    camera = Camera(offset=100.0, gain=0.5, flatfield=rng.uniform(0.8, 1.2, frames.shape[1:]))
    adu = frames * camera.flatfield / camera.gain + camera.offset
    return np.rint(adu).astype(np.uint16), camera


def main(out_dir: Path) -> None:
    rng = np.random.default_rng(15)
    fit_cuda._BATCH_BYTES = 8 * 49 * 32  # batches of 32 ROIs: both streams and slots are used
    np.savez(out_dir / "fits.npz", **fit_cases(rng))
    frames = movie(rng)
    for device in ("cpu", "cuda"):
        spots = localize(frames, roi_size=7, device=device, scheduler="synchronous")
        spots.to_parquet(out_dir / f"spots_{device}.parquet")
    adu, camera = as_stored(frames, rng)
    for device in ("cpu", "cuda"):  # synchronous: the simulator swaps `cuda` in the module
        spots = localize(  # that a kernel runs in, which other threads would then see
            adu, camera=camera, roi_size=7, device=device, chunk_frames=1, scheduler="synchronous"
        )
        spots.to_parquet(out_dir / f"camera_spots_{device}.parquet")
    noise = 1.5 * band_noise(frames)  # a given noise, as tracking mode passes for edge bands
    for device, detector in (("cpu", detect_arrays), ("cuda", detect_arrays_cuda)):
        found = detector(frames, roi_size=7, noise=noise)
        np.savez(out_dir / f"given_noise_{device}.npz", **found._asdict())


if __name__ == "__main__":
    main(Path(sys.argv[1]))

"""The CUDA engine against the CPU one, run under numba's CUDA simulator (no GPU needed).

The simulator must be on before ``numba.cuda`` is first imported, so `cuda_sim_cases.py` runs in a
subprocess; this session stays on the real CPU path. The CPU kernels are the reference: their own
tests hold them to the truth and the Cramér–Rao bound. Tolerances are the issue's (x, y within
2e-3 px, the same converged flag on >= 99 % of ROIs, the same spots from `localize`); both devices
run the same code in float64, so they agree far more closely.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import latentz

pytestmark = pytest.mark.slow  # about 20 s: the simulator runs each GPU thread as Python

POSITION_TOL_PX = 2e-3
SAME_FLAG_FRACTION = 0.99
FITS = ("mle_7x7", "wlsq_7x7", "lsq_7x7", "mle_9x11")


@pytest.fixture(scope="module")
def sim_out(tmp_path_factory):
    """The folder of cuda_sim_cases.py's outputs, run once under the simulator."""
    pytest.importorskip(
        "numba_cuda", reason="numba-cuda (the `gpu`/`test` extra) runs the CUDA simulator"
    )
    out = tmp_path_factory.mktemp("cuda_sim")
    src = str(Path(latentz.__file__).parents[1])
    env = {
        **os.environ,
        "NUMBA_ENABLE_CUDASIM": "1",
        "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")]),
    }
    script = Path(__file__).with_name("cuda_sim_cases.py")
    run = subprocess.run(
        [sys.executable, str(script), str(out)], env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def results(sim_out):
    fits = dict(np.load(sim_out / "fits.npz"))
    spots = {
        (movie, d): pd.read_parquet(sim_out / f"{movie}spots_{d}.parquet")
        for movie in ("", "camera_")
        for d in ("cpu", "cuda")
    }
    return fits, spots


@pytest.mark.parametrize("case", FITS)
def test_cuda_fits_match_the_cpu(results, case):
    fits, _ = results
    cpu = {k.split("_cpu_")[1]: v for k, v in fits.items() if k.startswith(f"{case}_cpu_")}
    gpu = {k.split("_cuda_")[1]: v for k, v in fits.items() if k.startswith(f"{case}_cuda_")}
    assert np.mean(cpu["converged"] == gpu["converged"]) >= SAME_FLAG_FRACTION
    both = cpu["converged"] & gpu["converged"]
    assert both.sum() >= 0.9 * both.size  # the comparison covers nearly every ROI
    shift = np.abs(cpu["params"][both, :2] - gpu["params"][both, :2])
    assert shift.max() <= POSITION_TOL_PX
    # the errors (the sandwich, computed on the CPU after either fit), the likelihood and the
    # iterations are the same computation
    np.testing.assert_allclose(gpu["errors"][both], cpu["errors"][both], rtol=1e-6)
    np.testing.assert_allclose(gpu["loglik"][both], cpu["loglik"][both], rtol=1e-9)
    assert np.mean(gpu["iterations"] == cpu["iterations"]) >= SAME_FLAG_FRACTION


def test_cuda_refuses_the_same_bad_rois(results):
    fits, _ = results
    for device in ("cpu", "cuda"):
        # ROI 0 holds a NaN pixel, ROI 1 no spot at all
        assert not fits[f"mle_7x7_{device}_converged"][0]
        assert np.isnan(fits[f"mle_7x7_{device}_params"][0]).all()
        assert fits[f"mle_7x7_{device}_iterations"][0] == 0
        assert not fits[f"mle_7x7_{device}_converged"][1]


def test_cuda_errors_cover_the_truth(results):
    """The CUDA fit's x, y errors cover about 68 % of the actual errors (binomial 3 sigma)."""
    fits, _ = results
    ok = fits["mle_7x7_cuda_converged"]
    actual = np.abs(fits["mle_7x7_cuda_params"][ok, :2] - fits["truth_7x7"][ok])
    covered = np.mean(actual <= fits["mle_7x7_cuda_errors"][ok, :2])
    n = actual.size
    assert abs(covered - 0.683) <= 3 * np.sqrt(0.683 * 0.317 / n)


@pytest.mark.parametrize("movie", ["", "camera_"], ids=["photons", "uint16 ADU, two chunks"])
def test_cuda_localize_finds_the_same_spots(results, movie):
    _, spots = results
    cpu, gpu = spots[movie, "cpu"], spots[movie, "cuda"]
    assert len(cpu) == len(gpu) >= 6  # every simulated emitter (one at the edge)
    assert cpu["edge"].any()
    for column in ("frame", "edge", "close_pair"):
        assert (cpu[column].to_numpy() == gpu[column].to_numpy()).all(), column
    # the CPU band-pass runs in float32 (relative rounding ~1e-7 per step), the GPU in float64
    np.testing.assert_allclose(gpu["snr"], cpu["snr"], rtol=1e-5)
    assert np.abs(gpu[["x", "y"]].to_numpy() - cpu[["x", "y"]].to_numpy()).max() <= POSITION_TOL_PX
    assert (gpu["converged"] == cpu["converged"]).all()


def test_cuda_detects_with_a_given_noise_as_the_cpu(sim_out):
    cpu, gpu = (dict(np.load(sim_out / f"given_noise_{d}.npz")) for d in ("cpu", "cuda"))
    assert len(cpu["row"]) >= 4
    for name in ("frame", "row", "col", "edge", "close_pair"):
        np.testing.assert_array_equal(gpu[name], cpu[name])
    np.testing.assert_allclose(gpu["snr"], cpu["snr"], rtol=1e-5)

"""Benchmark: where the z error of 1 µm emitters near a 1 µm particle calibration comes from.

The dataset and emitters of ``tests/calibration/test_show_simulated.py`` (latentz's simulator:
300 particles of 1 µm, ±24 nm in diameter; 40 emitters of 1 µm, 4-10 px from a calibration
particle, at 0.3x its photons; ``rho_w``, ``nearest``), for several draws of emitters. Each
emitter's z error is split by localizing it again without noise, and without noise at the
calibration's photons: *noise* (noisy minus noise-free), *brightness residual* (noise-free at
0.3x minus at 1x, what the brightness correction leaves), *field and bead* (noise-free at 1x
minus truth). Beside it, the nearest calibration particle's centre offset from the simulator's
truth, (diameter − 1000 nm) / 2, and the reported parts of ``z_err_nm``. RMS in nm. Writes
``results/bench_particle_offset.md``.

Run: ``python benchmarks/bench_particle_offset.py [--draws 11,12,13,14,15]``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from latentz.calibration.field_errors import field_sigma
from latentz.calibration.local_errors import model_sigma
from latentz.calibration.workflow import calibrate_traces

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests" / "calibration"))
from test_show_simulated import independent_emitters, simulated_calibration  # noqa: E402


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.square(values))))


def split(ds, cal, seed: int) -> dict[str, float]:
    """One draw of 40 emitters: the RMS of each part of the z error and of the reported σ."""
    z, spots = {}, None
    for name, kw in (("noisy", {}), ("clean", {"noise": False}),
                     ("bright", {"noise": False, "photons": 5e5})):  # fmt: skip
        found, z_true = independent_emitters(ds, cal, diameter_nm=1000.0, seed=seed, **kw)
        located = cal.apply(found)
        z[name] = located["z_nm"].to_numpy()
        spots = located if name == "noisy" else spots
    inside = spots["in_range"].to_numpy()
    p = spots["cal_particle"].to_numpy()
    _, idx = cKDTree(ds.truth[["field_x", "field_y"]].to_numpy()).query(cal.positions[p])
    offset = (ds.truth["diameter_nm"].to_numpy()[idx] - 1000.0) / 2
    distance = np.hypot(*(spots[["x", "y"]].to_numpy() - cal.positions[p]).T)
    local = model_sigma(cal, "z", p, z["noisy"])
    field = field_sigma(cal, "z", z["noisy"], distance)
    total = spots["z_err_nm"].to_numpy()
    fit = np.sqrt(np.maximum(total**2 - local**2 - field**2, 0.0))
    err = z["noisy"] - z_true
    bead = z["bright"] - z_true
    parts = {
        "RMSE": err,
        "noise": z["noisy"] - z["clean"],
        "brightness residual": z["clean"] - z["bright"],
        "field and bead": bead,
        "nearest particle's offset": offset,
        "field and bead, offset removed": bead + offset,
        "reported fit": fit,
        "reported local": local,
        "reported field": field,
        "reported": total,
    }
    row = {"draw": seed, "n": int(inside.sum())} | {k: _rms(v[inside]) for k, v in parts.items()}
    row["bias"] = float(np.mean(err[inside]))
    row["1σ covers"] = float(np.mean(np.abs(err[inside]) <= total[inside]))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", default="11,12,13,14,15", help="emitter seeds (11: the test's)")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    ds, cal, _, _ = simulated_calibration()
    rho_w = calibrate_traces(cal.traces, camera=cal.camera, shape="rho_w", field_model="nearest")
    table = pd.DataFrame([split(ds, rho_w, int(s)) for s in args.draws.split(",")])
    text = table.to_markdown(index=False, floatfmt=".3g")
    print(text)
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    tmp = out / "bench_particle_offset.md.tmp"
    tmp.write_text(
        "# Where the z error of 1 µm emitters near a 1 µm particle calibration comes from\n\n"
        f"`python benchmarks/bench_particle_offset.py {' '.join(sys.argv[1:])}` (RMS in nm; "
        "see the module docstring)\n\n" + text + "\n"
    )
    tmp.replace(out / "bench_particle_offset.md")


if __name__ == "__main__":
    main()

"""Ground-truth ROIs for the fit tests: eq. 1 rendered at pixel centres, with Poisson noise."""

import numpy as np
import pandas as pd

from latentz.fit import amplitude_of, render_rois


def truth_table(n, size, *, seed, photons=(1e3, 1e5), background=(10.0, 100.0), wmax=3.0):
    """Random emitters near the ROI centre: log-uniform photons, the issue's parameter ranges."""
    rng = np.random.default_rng(seed)
    c = (size - 1) / 2
    table = pd.DataFrame(
        {
            "x": c + rng.uniform(-0.5, 0.5, n),
            "y": c + rng.uniform(-0.5, 0.5, n),
            "photons": np.exp(rng.uniform(np.log(photons[0]), np.log(photons[1]), n)),
            "background": rng.uniform(*background, n),
            "wx": rng.uniform(1.0, wmax, n),
            "wy": rng.uniform(1.0, wmax, n),
            "rho": rng.uniform(-0.6, 0.6, n),
        }
    )
    table["amplitude"] = amplitude_of(table["photons"], table["wx"], table["wy"], table["rho"])
    return table


def noisy_rois(table, size, *, seed):
    """Poisson draws of the expected image of each row of ``table``."""
    rng = np.random.default_rng(seed)
    return rng.poisson(render_rois(table, shape=size)).astype(np.float64)

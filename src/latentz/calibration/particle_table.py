"""The table of a calibration's particles (:attr:`~latentz.calibration.result.Calibration.
particles`): one row per particle, with its place, focus, models' σ and range, culling and
polynomial coefficients."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from latentz.calibration.local import row_mean

if TYPE_CHECKING:
    from latentz.calibration.view import CalibrationView

__all__ = ["particle_table"]


def particle_table(cal: CalibrationView) -> pd.DataFrame:
    """One row per calibration particle; the columns are listed under
    :attr:`~latentz.calibration.result.Calibration.particles`."""
    local, traces = cal.local, cal.traces
    px = cal.camera.pixel_size_nm
    pos = cal.positions
    table = pd.DataFrame(
        {
            "particle": np.arange(len(traces)),
            "stack": traces.stack,
            "x": pos[:, 0],
            "y": pos[:, 1],
            "x_nm": pos[:, 0] * px,
            "y_nm": pos[:, 1] * px,
            "z_f": local.z_f + cal.plane(*(pos * px).T) + cal.heights_nm,
            "z_f_nm": local.z_f,
            "height_nm": cal.heights_nm,
            "in_focus": local.in_focus,
        }
    )
    for name, model in local.shapes.items():
        table[f"sigma_z_{name}"] = row_mean(model.sigma_z)
        table[f"z_min_{name}"] = model.z_range[:, 0]
        table[f"z_max_{name}"] = model.z_range[:, 1]
    table["sigma_z"] = table[f"sigma_z_{cal.shape}"]
    table["z_min_nm"] = table[f"z_min_{cal.shape}"]
    table["z_max_nm"] = table[f"z_max_{cal.shape}"]
    table["sigma_dx_nm"] = row_mean(local.sigma_dx) * px
    table["sigma_dy_nm"] = row_mean(local.sigma_dy) * px
    table["culled"] = cal.culled
    table["cull_reason"] = cal.reason
    table["reason"] = cal.reason
    for column in cal.scores.columns:
        table[f"score_{column}"] = cal.scores[column].to_numpy()
    model = local.shapes[cal.shape].inverse
    table["z_coef"] = list(model.coef)
    table["z_domain"] = list(model.domain)
    table["dx_coef"] = list(local.dx.coef)
    table["dy_coef"] = list(local.dy.coef)
    table["lateral_domain_nm"] = list(local.dx.domain)
    table["amplitude_coef"] = list(local.amplitude.coef)
    return table

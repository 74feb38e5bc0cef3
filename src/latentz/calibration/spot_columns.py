"""The fit columns of a spot table that :meth:`~latentz.calibration.result.Calibration.apply`
reads, as float64 arrays read once, and their stacks in :func:`~latentz.fit.api.fit_rois`'
order."""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentz.fit.api import CORRELATION_COLUMNS

__all__ = ["ERROR_COLUMNS", "PARAMS", "READ_COLUMNS", "SPOT_COLUMNS", "spot_arrays", "stacked"]

#: The columns every spot table to localize has.
SPOT_COLUMNS = ("x", "y", "amplitude", "wx", "wy", "rho")
#: The fit errors that propagate a spot's own precision to z.
ERROR_COLUMNS = ("amplitude_err", "wx_err", "wy_err", "rho_err")
PARAMS = ("x", "y", "amplitude", "background", "wx", "wy", "rho")  # fit_rois' order
#: The columns :meth:`~latentz.calibration.result.Calibration.apply` reads as arrays, where a
#: table has them.
READ_COLUMNS = (*PARAMS, *ERROR_COLUMNS, *CORRELATION_COLUMNS, "x_err", "y_err")


def spot_arrays(spots: pd.DataFrame) -> dict[str, np.ndarray]:
    """The spots' columns that :meth:`~latentz.calibration.result.Calibration.apply` reads
    (:data:`READ_COLUMNS`, those the table has) as float64 arrays, each read once."""
    return {c: spots[c].to_numpy(dtype=np.float64) for c in READ_COLUMNS if c in spots.columns}


def stacked(cols: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    """(n, len(names)) of the arrays ``cols`` under ``names``, NaN for a name it lacks."""
    n = len(cols["x"])
    return np.column_stack([cols[name] if name in cols else np.full(n, np.nan) for name in names])

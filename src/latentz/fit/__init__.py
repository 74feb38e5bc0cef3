"""Bivariate Gaussian fitting of emitter images (eq. 1 of Copeland et al. 2021).

`fit_rois` returns a table; `fit_arrays` is its array core; `render_rois` renders eq. 1 for ground
truth; `crlb` and `fisher_information` give the Cramér–Rao bounds of the model, and
`poisson_information` the information of any model's Jacobian under its noise model.
"""

from latentz.fit._model import (
    PARAMS,
    amplitude_of,
    crlb,
    fisher_information,
    moment_start,
    photons_of,
    poisson_information,
    render_rois,
)
from latentz.fit.api import FIT_COLUMNS, METHODS, FitResult, fit_arrays, fit_rois

__all__ = [
    "FIT_COLUMNS",
    "METHODS",
    "PARAMS",
    "FitResult",
    "amplitude_of",
    "crlb",
    "fisher_information",
    "fit_arrays",
    "fit_rois",
    "moment_start",
    "photons_of",
    "poisson_information",
    "render_rois",
]

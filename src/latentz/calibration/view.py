"""What the modules behind :class:`~latentz.calibration.result.Calibration`'s methods read of it.

Placing spots, their errors, the particles' curves and table, cross-validation and the widefield
models are computed by functions that take the calibration as ``cal``. They annotate it with
:class:`CalibrationView`, the members they use, which ``Calibration`` has: so they need not
import ``result.py``, which imports them. All z values are on the tilt-corrected axis (nm);
positions are camera pixels; n is the number of calibration particles, n_z their planes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import Field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from latentz.calibration.local import LocalModels
    from latentz.calibration.reference import ReferenceField
    from latentz.calibration.tilt import TiltPlane
    from latentz.calibration.traces import Traces
    from latentz.camera import Camera

__all__ = ["CalibrationView"]


class CalibrationView(Protocol):
    """A calibration as its helpers read it; :class:`~latentz.calibration.result.Calibration`
    documents each member."""

    #: A dataclass: cross-validation copies it with other particles culled
    #: (:func:`dataclasses.replace`).
    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]

    @property
    def camera(self) -> Camera:
        """The camera the calibration stacks were taken with (pixel size, read noise)."""

    @property
    def traces(self) -> Traces:
        """Per-plane fit results of the calibration particles, (n, n_z) each."""

    @property
    def local(self) -> LocalModels:
        """Every particle's local models on the tilt-corrected axis."""

    @property
    def plane(self) -> TiltPlane:
        """Plane of best focus over the substrate (piezo z, nm)."""

    @property
    def culled(self) -> np.ndarray:
        """(n,) whether each particle was culled."""

    @property
    def reason(self) -> np.ndarray:
        """(n,) why each particle was culled ("" where it was kept)."""

    @property
    def scores(self) -> pd.DataFrame:
        """Robust z-scores of the culling features, one row per particle."""

    @property
    def options(self) -> dict[str, Any]:
        """Every option the calibration was made with."""

    @property
    def _cache(self) -> dict[str, Any]:
        """What is computed once per calibration, by name."""

    @property
    def shape(self) -> str:
        """The shape parameter of axial localization."""

    @property
    def roi_size(self) -> int:
        """Side of the ROI the calibration spots were fitted in, pixels."""

    @property
    def kept(self) -> np.ndarray:
        """Indices of the particles that were not culled."""

    @property
    def positions(self) -> np.ndarray:
        """(n, 2) camera position (x, y) of every particle, pixels."""

    @property
    def heights_nm(self) -> np.ndarray:
        """(n,) each particle's own height taken off its models, nm."""

    @property
    def usable_planes(self) -> np.ndarray:
        """(n, n_z) mask of each particle's planes where σ_z stays near its best."""

    @property
    def z_span_nm(self) -> np.ndarray:
        """(n, 2) lowest and highest z (nm) of the planes each particle's models were fitted to."""

    @property
    def width_range_px(self) -> tuple[float, float]:
        """Smallest and largest fitted width of the kept particles' traces, pixels."""

    @property
    def field_model(self) -> str:
        """How models are carried across the field ("auto" resolved)."""

    @property
    def crossval(self) -> pd.DataFrame:
        """Held-out errors of every field model."""

    def crossval_of(self, kind: str) -> pd.DataFrame:
        """The held-out errors of field model ``kind``."""

    @property
    def widefield(self) -> Callable[..., tuple[np.ndarray, ...]] | None:
        """The widefield model: ``(x, y, s, iterations=...)`` to z (nm), Δx', Δy' (px) and
        in_range; None for ``field_model="nearest"``."""

    @property
    def reference_field(self) -> ReferenceField:
        """A-normalised shapes' reference amplitude across the field."""

    @property
    def noise_scale(self) -> float:
        """Factor (≤ 1) on the fit's part of ``z_err_nm`` over all z."""

    def curves_at(self, particle: Any, z_nm: Any) -> dict[str, np.ndarray]:
        """Curves wx, wy (px) and ρ of particles ``particle`` at ``z_nm``, and their scatter."""

    def inverse_z(self, s: np.ndarray, p: np.ndarray, *, shape: str | None = None) -> np.ndarray:
        """z (nm) of shape values ``s`` by particles ``p``' inverse models; NaN outside them."""

    def local_z(self, value: Any, *, shape: str | None = None) -> np.ndarray:
        """(n,) z (nm) of every particle for one shape value."""

    def local_delta(self, z_nm: Any) -> tuple[np.ndarray, np.ndarray]:
        """(n,) Δx'(z), Δy'(z) (pixels) of every particle at ``z_nm``."""

    def in_range_window(self, p: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(m, 2) the z (nm) where a spot placed at ``z`` by particle ``p`` can lie in range."""

    def nearest(self, x: Any, y: Any) -> np.ndarray:
        """Index of the nearest kept particle to each (x, y) camera position."""

    def reference_sigma_nm(self, axis: str) -> float:
        """1σ (nm) of the particles' lateral reference on ``axis`` ("x" or "y")."""

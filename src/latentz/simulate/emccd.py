"""An EMCCD readout: shot noise, a gamma-distributed electron multiplication, read noise.

``n`` photoelectrons (Poisson) leave the gain register as a gamma-distributed charge of shape
``n`` and scale ``em_gain`` (mean ``n G``, variance ``n G²``): with the shot noise, the variance is
``2 n G²``, an excess noise factor of √2. Read noise (electrons at the output, so it shrinks by
``G`` referred to the input), the conversion to ADU, an offset, rounding and 16-bit clipping
follow. The latentz camera of the same frames is ``Camera.emccd(offset=offset_adu, gain=e_per_adu
/ em_gain, readnoise=readnoise_e / em_gain)``: photoelectrons per ADU and input-referred read
noise, halved to Poisson-equivalent counts (:meth:`latentz.camera.Camera.emccd`).
"""

from __future__ import annotations

import numpy as np

from latentz._shared.validate import check_positive
from latentz.simulate._render import ADU_MAX

__all__ = ["expose_emccd"]


def expose_emccd(
    expected: np.ndarray,
    rng: np.random.Generator,
    *,
    em_gain: float,
    e_per_adu: float,
    readnoise_e: float,
    offset_adu: float,
) -> np.ndarray:
    """ADU (uint16, the shape of ``expected``) from expected photoelectrons per pixel.

    ``em_gain``: mean electrons out per photoelectron; ``e_per_adu``: output electrons per ADU;
    ``readnoise_e``: read-noise standard deviation in output electrons; ``offset_adu``: baseline.
    """
    em_gain = check_positive("em_gain", em_gain)
    e_per_adu = check_positive("e_per_adu", e_per_adu)
    readnoise_e = check_positive("readnoise_e", readnoise_e, allow_zero=True)
    electrons = rng.poisson(np.asarray(expected, dtype=np.float64))
    charge = rng.gamma(electrons, em_gain)  # shape 0 gives 0
    charge += rng.normal(0.0, readnoise_e, size=charge.shape)
    adu = np.rint(charge / e_per_adu + offset_adu)
    return np.clip(adu, 0, ADU_MAX).astype(np.uint16)

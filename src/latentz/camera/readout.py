"""Global-shutter readout: imaging frequency, and its trade-off against centroid precision.

With a global shutter the whole sensor exposes for ``τ_e``, then pixel rows are read out in pairs,
so one frame takes ``τ_e + n_prp × t_prp`` with ``n_prp = n_rows / 2`` row pairs (paper, Methods,
"Microsystem imaging"). Reading fewer rows raises the rate but, over a uniformly bright field,
collects fewer signal photons for a rigid transformation (Supp. Fig. 22).

The paper rounds the time per row pair to 10 µs but states a 10 ms readout of the full
2048-row sensor and 90.9 Hz at 1 ms exposure; those two figures fix ``t_prp`` = 10 ms / 1024
= 9.766 µs, the default here (10 µs would give 89.0 Hz).
"""

from __future__ import annotations

import numpy as np

from latentz._shared.validate import check_positive

__all__ = ["ROW_PAIR_US", "frame_rate_hz", "constellation_precision_nm", "readout_figure"]

#: Readout time per pair of pixel rows, µs: the paper's 10 ms full-sensor readout / 1024 pairs.
ROW_PAIR_US = 10_000.0 / 1024


def _positive_array(name: str, value) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(array)) or np.any(array <= 0):
        raise ValueError(f"Expected `{name}` to be finite and > 0, got {value!r}.")
    return array


def frame_rate_hz(exposure_ms, n_rows, row_pair_us: float = ROW_PAIR_US):
    """Global-shutter imaging frequency ``1 / (τ_e + n_rows/2 × row_pair_us)``, Hz.

    Parameters
    ----------
    exposure_ms : float or array
        Exposure time τ_e, ms (> 0).
    n_rows : int or array
        Pixel rows read out (the readout extent), > 0; a pair of rows reads in ``row_pair_us``.
    row_pair_us : float
        Readout time of one pair of rows, µs.

    Returns
    -------
    float or ndarray, Hz.

    Examples
    --------
    >>> round(frame_rate_hz(1.0, 2048), 1)
    90.9
    >>> round(frame_rate_hz(1.0, 2048, row_pair_us=10.0), 1)
    89.0
    """
    tau_ms = _positive_array("exposure_ms", exposure_ms)
    rows = _positive_array("n_rows", n_rows)
    pair_us = check_positive("row_pair_us", row_pair_us)
    rate = 1e3 / (tau_ms + rows / 2 * pair_us * 1e-3)
    return float(rate) if rate.ndim == 0 else rate


def constellation_precision_nm(
    exposure_ms,
    n_rows,
    *,
    photons_per_ms: float,
    psf_sigma_nm: float,
    full_rows: int = 2048,
):
    """Shot-noise limit of a constellation centroid, ``σ_psf / √N``, nm (Supp. Fig. 22b).

    As in the paper's calculation, signal photons arrive uniformly over the field, so a readout
    of ``n_rows`` of ``full_rows`` rows collects ``N = photons_per_ms × τ_e × n_rows/full_rows``
    photons from all emitters together.

    Parameters
    ----------
    exposure_ms, n_rows : float or array
        Exposure time, ms, and rows read out.
    photons_per_ms : float
        Signal photons per ms from every emitter in the full field together.
    psf_sigma_nm : float
        Standard deviation of the point spread function, nm.
    full_rows : int
        Rows of the full sensor.
    """
    tau_ms = _positive_array("exposure_ms", exposure_ms)
    rows = _positive_array("n_rows", n_rows)
    rate = check_positive("photons_per_ms", photons_per_ms)
    sigma = check_positive("psf_sigma_nm", psf_sigma_nm)
    photons = rate * tau_ms * rows / check_positive("full_rows", full_rows)
    precision = sigma / np.sqrt(photons)
    return float(precision) if precision.ndim == 0 else precision


def readout_figure(
    *,
    n_rows=(2048, 1024, 512, 256, 128),
    exposure_ms=(0.1, 10.0),
    photons_per_ms: float = 28 * 1e5,
    psf_sigma_nm: float = 300.0,
    used=(1.0, 2048),
):
    """Supp. Fig. 22: (a) imaging frequency and (b) centroid precision against exposure time,
    one line per readout extent; a dot marks ``used`` (exposure ms, rows).

    The default photon rate (28 emitters of 10⁵ photons per ms, the paper's constellation) and
    PSF width are illustrative: pass the values of your own emitters.
    """
    import matplotlib.pyplot as plt

    tau = np.geomspace(*exposure_ms, 200)
    fig, (ax_rate, ax_prec) = plt.subplots(1, 2, figsize=(9.5, 3.8), constrained_layout=True)
    for rows in n_rows:
        ax_rate.plot(tau, frame_rate_hz(tau, rows), label=f"{rows} rows")
        ax_prec.plot(
            tau,
            constellation_precision_nm(
                tau, rows, photons_per_ms=photons_per_ms, psf_sigma_nm=psf_sigma_nm
            ),
        )
    tau_used, rows_used = used
    ax_rate.plot(tau_used, frame_rate_hz(tau_used, rows_used), "ko")
    ax_prec.plot(
        tau_used,
        constellation_precision_nm(
            tau_used, rows_used, photons_per_ms=photons_per_ms, psf_sigma_nm=psf_sigma_nm
        ),
        "ko",
    )
    for ax, label in ((ax_rate, "imaging frequency (Hz)"), (ax_prec, "centroid precision (nm)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("exposure time (ms)")
        ax.set_ylabel(label)
    ax_rate.legend(fontsize=8)
    ax_rate.set_title("a  global-shutter imaging frequency")
    ax_prec.set_title(f"b  shot-noise limit ({photons_per_ms:.3g} photons/ms, full field)")
    return fig

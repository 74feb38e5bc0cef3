"""Held-out z error of dim emitters made from the calibration particles' own images.

A typical single emitter (10³–10⁴ photons) is not a calibration particle: its fit sees the
background over its whole ROI, a truncated defocused spot and a ring the Gaussian does not
model, and ``apply`` corrects its background bias with the refits of the particle nearest it.
How much each of these costs depends on the ROI, and no bound on an ideal Gaussian sees all of
them. So each kept particle's image at every plane is made into such an emitter: its light
above the images' background (:func:`~latentz.calibration.roi.frame_background`) scaled to
``photons``, over that background, with Poisson and read noise; it is fitted as ``localize``
fits, placed at the nearest *other* kept particle (whose models, field and dimming refits then
localize it, as a spot there would be), and ``Calibration.apply`` gives its z. The error is
that z minus the plane's (tilt-corrected) z of the particle the image came from.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from latentz.fit import fit_rois
from latentz.fit._model import photons_of

if TYPE_CHECKING:
    from latentz.calibration.result import Calibration
    from latentz.camera import Camera

__all__ = ["emitter_errors", "particle_images"]


def particle_images(
    cal: Calibration, stacks: list[np.ndarray], camera: Camera, rows: np.ndarray
) -> np.ndarray:
    """(len(rows), n_z, roi, roi) photons of the ``rows`` particles' ROIs at every plane, cut
    as calibration cuts them (centred on the particle's median position in its stack)."""
    from latentz.calibration.traces import _roi_corners

    roi, traces = cal.roi_size, cal.traces
    local_xy = traces.position()[rows] - traces.offset_px[rows]
    out = np.empty((rows.size, traces.z_nm.size, roi, roi))
    plain = replace(camera, flatfield=None)
    for s in np.unique(traces.stack[rows]):
        own = np.flatnonzero(traces.stack[rows] == s)
        corners = _roi_corners(local_xy[own], stacks[s].shape[1:], roi)
        r = corners[:, 0, None] + np.arange(roi)
        c = corners[:, 1, None] + np.arange(roi)
        cut = stacks[s][:, r[:, :, None], c[:, None, :]].transpose(1, 0, 2, 3)
        out[own] = plain.to_photons(cut)
    return out


def emitter_errors(
    cal: Calibration,
    stacks: list[np.ndarray],
    camera: Camera,
    background: np.ndarray,
    photons: float,
    *,
    seed: int = 0,
) -> np.ndarray:
    """(n, n_z) z error (nm) of an emitter of ``photons`` photons made from each kept
    particle's image at each plane over ``background`` ((n_stacks, n_z) photons per pixel) and
    localized as a spot at its nearest other kept particle (module notes; a lone particle's at
    its own place); NaN for the other particles, ``inf`` where the emitter is not localized in
    range."""
    traces, n_z = cal.traces, cal.traces.z_nm.size
    errors = np.full((len(traces), n_z), np.nan)
    rows = cal.kept
    if rows.size == 0:
        return errors
    neighbour = rows  # a lone particle is its own neighbour: its error is not held out
    if rows.size > 1:
        neighbour = rows[cKDTree(cal.positions[rows]).query(cal.positions[rows], k=2)[1][:, 1]]
    images = particle_images(cal, stacks, camera, rows)
    bg = background[traces.stack[rows]][:, :, None, None]  # (k, n_z, 1, 1)
    brightness = np.nanmedian(
        photons_of(traces["amplitude"], traces["wx"], traces["wy"], traces["rho"])[rows], axis=1
    )
    scale = (photons / brightness)[:, None, None, None]
    mean = np.clip((images - bg) * scale + bg, 0.0, None)
    rng = np.random.default_rng([seed, cal.roi_size, int(photons)])
    noisy = rng.poisson(mean) + rng.normal(0.0, camera.readnoise, mean.shape)
    fit_camera = replace(camera, offset=0.0, gain=1.0, flatfield=None)
    roi = cal.roi_size
    table = fit_rois(noisy.reshape(-1, roi, roi), method=cal.method, camera=fit_camera)
    to = cal.positions[neighbour]  # each image placed at its nearest other particle
    spots = table.assign(x=np.repeat(to[:, 0], n_z), y=np.repeat(to[:, 1], n_z))
    spots.attrs["roi_size"] = roi
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # widths outside the calibration's: out of range here
        # scored with the one-value readout: the joint one reads z far from focus better in a
        # larger ROI, whose lateral cost for dim molecules this z-only score does not see
        located = cal.apply(spots, z_readout="shape")
    z = np.where(located["in_range"].to_numpy(bool), located["z_nm"].to_numpy(float), np.inf)
    errors[rows] = z.reshape(rows.size, n_z) - cal.local.z_nm[rows]
    return errors

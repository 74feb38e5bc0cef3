"""Where the CLI's camera comes from, said out loud: the command line (or a camera file), the
image file's metadata, or an estimate from the images.

- ``pixel_size_nm``: given, else the file's metadata (OME-TIFF ``PhysicalSizeX``, ImageJ
  resolution and unit, MicroManager ``PixelSize_um``), else latentz's default with a line
  asking for it (images cannot tell it).
- ``offset`` (ADU): given, else the image minimum: a pixel with no light reads the offset plus
  read noise, and a stack has such pixels; it is within a few read-noise standard deviations
  of the offset.
- ``gain`` (photoelectrons per ADU): given, else the photon-transfer curve of the stack. Two
  neighbouring planes of a through-focus stack hold nearly the same image, so half the squared
  difference of a pixel between them is its noise variance; binned by the pixel's mean, it
  grows as ``(mean − offset) / gain``: the slope is ``1 / gain``. An EMCCD's excess noise
  doubles the variance, so there it estimates half the gain (the effective one).
- ``readnoise``: given, else the default.

On an EMCCD (``emccd``) a given gain and read noise are the datasheet's, halved to the
Poisson-equivalent counts of :meth:`~latentz.camera.Camera.emccd`; the photon-transfer estimate
is Poisson-equivalent already.
"""

from __future__ import annotations

import os
from dataclasses import fields
from typing import Any

import numpy as np

from latentz.camera import Camera
from latentz.camera.model import poisson_equivalent

__all__ = [
    "pixel_size_from_metadata",
    "estimate_offset",
    "estimate_gain",
    "camera_for_stacks",
]

_UNIT_NM = {"nm": 1.0, "nanometer": 1.0, "µm": 1e3, "um": 1e3, "micron": 1e3, "\\u00b5m": 1e3}
_UNIT_NM["mm"] = 1e6
_UNIT_NM["micrometer"] = 1e3


def pixel_size_from_metadata(path: str | os.PathLike) -> tuple[float, str] | None:
    """(pixel size in nm, which metadata) from an OME-TIFF, ImageJ or MicroManager TIFF; None
    when the file does not record it."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        if tif.is_ome and tif.ome_metadata:
            import xml.etree.ElementTree as ET

            for element in ET.fromstring(tif.ome_metadata).iter():
                if element.tag.endswith("Pixels") and "PhysicalSizeX" in element.attrib:
                    unit = element.attrib.get("PhysicalSizeXUnit", "µm")
                    size = float(element.attrib["PhysicalSizeX"]) * _UNIT_NM.get(unit, 1e3)
                    return size, "OME-TIFF PhysicalSizeX"
        micromanager = tif.micromanager_metadata or {}
        summary = micromanager.get("Summary", {}) if isinstance(micromanager, dict) else {}
        if summary.get("PixelSize_um"):
            return float(summary["PixelSize_um"]) * 1e3, "MicroManager PixelSize_um"
        imagej = tif.imagej_metadata or {}
        unit = str(imagej.get("unit", "")).lower()
        tag = tif.pages[0].tags.get("XResolution")
        if unit in _UNIT_NM and tag is not None:
            numerator, denominator = tag.value
            if numerator > 0:
                return denominator / numerator * _UNIT_NM[unit], "ImageJ resolution"
    return None


def estimate_offset(stacks: list[Any]) -> float:
    """The image minimum over (a sample of) the stacks' planes, ADU."""
    return float(min(np.min(np.asarray(st[:: max(1, len(st) // 16)])) for st in stacks))


def estimate_gain(stacks: list[Any], *, n_bins: int = 40) -> float:
    """Photoelectrons per ADU from the photon-transfer curve of neighbouring planes (module
    docstring); NaN when the curve has no positive slope."""
    means, variances = [], []
    for stack in stacks:
        stack = np.asarray(stack, dtype=np.float64)
        if stack.shape[0] < 2:
            continue
        a, b = stack[:-1], stack[1:]
        means.append(((a + b) / 2).ravel())
        variances.append(((a - b) ** 2 / 2).ravel())
    if not means:
        return np.nan
    mean, variance = np.concatenate(means), np.concatenate(variances)
    edges = np.quantile(mean, np.linspace(0.0, 0.999, n_bins + 1))
    which = np.clip(np.searchsorted(edges, mean) - 1, 0, n_bins - 1)
    counts = np.bincount(which, minlength=n_bins)
    full = counts > 50
    if full.sum() < 3:
        return np.nan
    m = np.bincount(which, mean, n_bins)[full] / counts[full]
    v = np.bincount(which, variance, n_bins)[full] / counts[full]
    slope = np.polyfit(m, v, 1)[0]
    return float(1.0 / slope) if slope > 0 else np.nan


def camera_for_stacks(
    stacks: list[Any],
    path: str | os.PathLike | None,
    given: dict[str, Any],
    *,
    flatfield: np.ndarray | None = None,
    emccd: bool = False,
) -> tuple[Camera, str]:
    """The camera for calibration stacks, and one line saying where each value came from.

    ``given`` holds the values from the command line or a camera file (None where absent);
    ``emccd``: they are an EMCCD's, whose given gain and read noise are halved.
    """
    default = Camera()
    values, sources = {}, {}
    halved = poisson_equivalent(given, emccd)
    for name in ("offset", "gain", "readnoise", "pixel_size_nm"):
        if given.get(name) is not None:
            values[name] = float(halved[name])
            sources[name] = "given, halved: EMCCD" if halved[name] != given[name] else "given"
    if "pixel_size_nm" not in values:
        found = pixel_size_from_metadata(path) if path is not None else None
        if found is not None:
            values["pixel_size_nm"], sources["pixel_size_nm"] = found[0], found[1]
        else:
            values["pixel_size_nm"] = default.pixel_size_nm
            sources["pixel_size_nm"] = "default: not in the file, give --pixel-size-nm"
    if "offset" not in values:
        values["offset"], sources["offset"] = estimate_offset(stacks), "estimated: image minimum"
    if "gain" not in values:
        gain = estimate_gain(stacks)
        if np.isfinite(gain):
            values["gain"], sources["gain"] = gain, "estimated: photon-transfer curve"
        else:
            values["gain"] = default.gain
            sources["gain"] = "default: no photon-transfer curve, give --gain"
    if "readnoise" not in values:
        values["readnoise"], sources["readnoise"] = default.readnoise, "default"
    units = {"offset": "ADU", "gain": "e-/ADU", "readnoise": "e-", "pixel_size_nm": "nm"}
    names = {f.name: f.name.replace("_nm", "").replace("_", " ") for f in fields(Camera)}
    line = "camera: " + ", ".join(
        f"{names[k]} {values[k]:.4g} {units[k]} ({sources[k]})" for k in units
    )
    return Camera(**values, flatfield=flatfield), line

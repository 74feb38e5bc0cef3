"""A Calibration as plain arrays, and its HDF5 file (local stage).

Every part of a :class:`~latentz.calibration.result.Calibration` is arrays plus a few
scalars and options, so it flattens to ``{"group/name": ndarray}``. :func:`save` writes that
mapping to HDF5 (one dataset per key, options, camera and provenance as JSON attributes) through
an atomic temporary file; :func:`load` reads it back bit for bit. The widefield models (the
tables that ``apply`` interpolates) are stored under ``widefield/``, so a loaded calibration applies
them without re-tabulating, and the cross-validation tables under ``crossval/`` (format 3), so
a loaded calibration reports the same uncertainties. Format 1 files (before the widefield group)
are still read: their widefield models are rebuilt from the local models, which gives the same
tables; format 1 and 2 files recompute the cross-validation on first use.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pandas as pd

from latentz._shared.atomic import atomic_path
from latentz._version import __version__

__all__ = ["to_arrays", "from_arrays", "save", "load", "FORMAT"]

FORMAT = "latentz-calibration/3"
_READABLE = (FORMAT, "latentz-calibration/2", "latentz-calibration/1")
_CV_TEXT = ("model",)  # cross-validation columns stored as bytes
#: Field models rebuilt from the local models on load, with no tables to store.
_UNTABULATED = ("nearest", "curves")
T = TypeVar("T")


def _poly(prefix: str, model) -> dict[str, np.ndarray]:
    return {f"{prefix}/coef": model.coef, f"{prefix}/domain": model.domain}


def to_arrays(cal) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(arrays, attributes)``: every array of the calibration by key, and its JSON-able
    scalars (options, camera, tilt plane, θ)."""
    local, traces = cal.local, cal.traces
    arrays: dict[str, np.ndarray] = {
        "traces/z_nm": traces.z_nm,
        "traces/stack": traces.stack,
        "traces/crowded": traces.crowded,
        "traces/offset_px": traces.offset_px,
        **{f"traces/data/{k}": v for k, v in traces.data.items()},
        "local/z_nm": local.z_nm,
        "local/z_f": local.z_f,
        "local/in_focus": local.in_focus,
        "local/sigma_dx": local.sigma_dx,
        "local/sigma_dy": local.sigma_dy,
        **_poly("local/amplitude", local.amplitude),
        **_poly("local/dx", local.dx),
        **_poly("local/dy", local.dy),
        "culling/culled": cal.culled,
        "culling/reason": np.asarray(cal.reason, dtype=str).astype(bytes),
        **{f"culling/scores/{k}": cal.scores[k].to_numpy() for k in cal.scores.columns},
    }
    for name, shape in local.shapes.items():
        base = f"local/shapes/{name}"
        arrays.update(
            {
                f"{base}/values": shape.values,
                f"{base}/z_range": shape.z_range,
                f"{base}/sigma_z": shape.sigma_z,
                f"{base}/amplitude_ref": shape.amplitude_ref,
                **_poly(f"{base}/forward", shape.forward),
                **_poly(f"{base}/inverse", shape.inverse),
            }
        )
    if cal.camera.flatfield is not None:
        arrays["camera/flatfield"] = cal.camera.flatfield
    attrs = {
        "format": FORMAT,
        "version": __version__,
        "options": cal.options,
        "camera": cal.camera.as_dict(),
        "plane": [cal.plane.c0, cal.plane.cx, cal.plane.cy],
        "theta": local.theta,
        "n_scores": len(cal.scores),
        "provenance": cal.provenance,
    }
    if cal.field_model not in _UNTABULATED:
        wide, attrs["widefield"] = cal.widefield.as_arrays()
        arrays.update({f"widefield/{k}": v for k, v in wide.items()})
    attrs["field_model"] = cal.field_model  # the model "auto" chose
    cal.crossval_of(cal.field_model)  # the uncertainties need it: always stored
    kinds = [k[len("crossval/") :] for k in cal._cache if k.startswith("crossval/")]
    attrs["crossval"] = kinds
    for kind in kinds:
        for column, values in cal._cache[f"crossval/{kind}"].items():
            values = values.to_numpy()
            arrays[f"crossval/{kind}/{column}"] = (
                values.astype(str).astype(bytes) if column in _CV_TEXT else values
            )
    return arrays, attrs


def from_arrays(arrays: dict[str, np.ndarray], attrs: dict[str, Any], *, factory: type[T]) -> T:
    """Rebuild the calibration that :func:`to_arrays` flattened, as ``factory(...)`` (the
    :class:`~latentz.calibration.Calibration` class)."""
    from latentz.calibration.crossval import CROSSVAL_COLUMNS
    from latentz.calibration.local import LocalModels, ShapeModel
    from latentz.calibration.polymodel import PolyModel
    from latentz.calibration.tilt import TiltPlane
    from latentz.calibration.traces import Traces
    from latentz.camera import Camera

    if attrs.get("format") not in _READABLE:
        raise ValueError(f"Not a latentz calibration (format {attrs.get('format')!r}).")

    def poly(prefix: str) -> PolyModel:
        return PolyModel(arrays[f"{prefix}/coef"], arrays[f"{prefix}/domain"])

    def group(prefix: str) -> dict[str, np.ndarray]:
        return {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}

    names = sorted({k.split("/")[2] for k in arrays if k.startswith("local/shapes/")})
    shapes = {
        name: ShapeModel(
            values=arrays[f"local/shapes/{name}/values"],
            forward=poly(f"local/shapes/{name}/forward"),
            inverse=poly(f"local/shapes/{name}/inverse"),
            z_range=arrays[f"local/shapes/{name}/z_range"],
            sigma_z=arrays[f"local/shapes/{name}/sigma_z"],
            amplitude_ref=arrays[f"local/shapes/{name}/amplitude_ref"],
        )
        for name in names
    }
    local = LocalModels(
        z_nm=arrays["local/z_nm"],
        z_f=arrays["local/z_f"],
        in_focus=arrays["local/in_focus"],
        amplitude=poly("local/amplitude"),
        dx=poly("local/dx"),
        dy=poly("local/dy"),
        sigma_dx=arrays["local/sigma_dx"],
        sigma_dy=arrays["local/sigma_dy"],
        shapes=shapes,
        theta=attrs["theta"],
    )
    traces = Traces(
        arrays["traces/z_nm"],
        group("traces/data/"),
        stack=arrays["traces/stack"],
        crowded=arrays["traces/crowded"],
        offset_px=arrays["traces/offset_px"],
    )
    camera = Camera(**attrs["camera"], flatfield=arrays.get("camera/flatfield"))
    scores = pd.DataFrame(group("culling/scores/"), index=np.arange(attrs["n_scores"]))
    cal = factory(
        camera=camera,
        traces=traces,
        local=local,
        plane=TiltPlane(*attrs["plane"]),
        culled=arrays["culling/culled"],
        reason=np.array([r.decode() for r in arrays["culling/reason"]], dtype=object),
        scores=scores,
        options=attrs["options"],
        provenance=attrs.get("provenance") or {},
    )
    if "field_model" in attrs and cal.options.get("field_model") == "auto":
        cal._cache["chosen_field_model"] = attrs["field_model"]
    for kind in attrs.get("crossval", []):
        table = pd.DataFrame(group(f"crossval/{kind}/"))
        for column in _CV_TEXT:
            table[column] = [v.decode() for v in table[column]]
        cal._cache[f"crossval/{kind}"] = table[list(CROSSVAL_COLUMNS)]
    if "widefield" in attrs:
        from latentz.calibration.widefield import WidefieldModel

        cal._cache["widefield"] = WidefieldModel.from_arrays(
            group("widefield/"), attrs["widefield"]
        )
    elif attrs["format"] != "latentz-calibration/1" and cal.field_model not in _UNTABULATED:
        raise KeyError("widefield")
    return cal


def save(cal, path: str | os.PathLike, *, provenance: dict[str, Any] | None = None) -> None:
    """Write ``cal`` to the HDF5 file ``path`` atomically (``provenance``: extra JSON-able
    information such as input file names and hashes)."""
    import h5py

    from latentz._shared.provenance import stamp

    arrays, attrs = to_arrays(cal)
    # the version and date of this save, unless the calibration already records them
    record = {**stamp(), **cal.provenance, **(provenance or {})}
    attrs = {**attrs, "provenance": record}
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        for key, value in arrays.items():
            h5.create_dataset(key, data=value)
        for key, value in attrs.items():
            h5.attrs[key] = json.dumps(value)


def load(path: str | os.PathLike, *, factory: type[T]) -> T:
    """Read a calibration written by :func:`save`, built as ``factory(...)``."""
    import h5py

    source = Path(path)
    if not source.exists():
        raise FileNotFoundError(f"No such calibration file: {source}")
    arrays: dict[str, np.ndarray] = {}
    try:
        with h5py.File(source, "r") as h5:
            h5.visititems(
                lambda key, obj: (
                    arrays.__setitem__(key, obj[()]) if isinstance(obj, h5py.Dataset) else None
                )
            )
            attrs = {key: json.loads(value) for key, value in h5.attrs.items()}
    except (OSError, ValueError) as exc:
        raise ValueError(f"Cannot read {source.name} as a latentz calibration: {exc}") from exc
    found = attrs.get("format")
    if found not in _READABLE:
        raise ValueError(
            f"{source.name} is not a calibration this latentz ({__version__}) can read: format "
            f"{found!r} (written by latentz {attrs.get('version', '?')}), expected {FORMAT!r}."
        )
    try:
        return from_arrays(arrays, attrs, factory=factory)
    except KeyError as exc:
        raise ValueError(
            f"{source.name} is a damaged latentz calibration: {exc.args[0]!r} is missing."
        ) from exc
    except ValueError as exc:  # inconsistent or incomplete arrays of a stored model
        raise ValueError(f"{source.name} is a damaged latentz calibration: {exc}") from exc

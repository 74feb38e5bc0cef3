"""Validation helpers for the public API.

Each helper raises ``ValueError`` or ``TypeError`` whose message names the parameter and the value
received, so that a user sees at once what to change.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_array(
    name: str,
    value: Any,
    *,
    ndim: int | Iterable[int] | None = None,
    dtype_kind: str = "uifb",
    allow_empty: bool = False,
) -> np.ndarray:
    """Return ``value`` as an ndarray after checking its rank, dtype kind and size.

    ``ndim`` may be one rank or several; ``dtype_kind`` lists accepted ``dtype.kind`` letters.
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:  # noqa: BLE001 - anything that is not array-like
        raise TypeError(f"Expected `{name}` to be array-like, got {_describe(value)}.") from exc
    if arr.dtype.kind not in dtype_kind:
        raise TypeError(
            f"Expected `{name}` to have a numeric dtype ({dtype_kind!r}), got dtype {arr.dtype}."
        )
    if ndim is not None:
        ranks = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in ranks:
            want = " or ".join(str(r) for r in ranks)
            raise ValueError(f"Expected `{name}` to have {want} dimensions, got shape {arr.shape}.")
    if not allow_empty and arr.size == 0:
        raise ValueError(f"Expected `{name}` to be non-empty, got shape {arr.shape}.")
    return arr


def check_positive(name: str, value: Any, *, allow_zero: bool = False) -> float:
    """Return ``value`` as a finite float that is > 0 (or >= 0 with ``allow_zero``)."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"Expected `{name}` to be a number, got {_describe(value)}.") from exc
    if not np.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"Expected `{name}` to be finite and {bound}, got {value!r}.")
    return number


def check_finite(name: str, value: Any) -> float:
    """Return ``value`` as a finite float."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"Expected `{name}` to be a number, got {_describe(value)}.") from exc
    if not np.isfinite(number):
        raise ValueError(f"Expected `{name}` to be finite, got {value!r}.")
    return number


def check_int(name: str, value: Any, *, minimum: int | None = None) -> int:
    """Return ``value`` as an int, optionally >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"Expected `{name}` to be an integer, got {_describe(value)}.")
    if minimum is not None and value < minimum:
        raise ValueError(f"Expected `{name}` to be >= {minimum}, got {value}.")
    return int(value)


def check_choice(name: str, value: Any, choices: Iterable[str]) -> str:
    """Return ``value`` if it is one of ``choices``."""
    options = tuple(choices)
    if value not in options:
        listed = ", ".join(repr(c) for c in options)
        raise ValueError(f"Expected `{name}` to be one of {listed}, got {value!r}.")
    return value


def check_columns(name: str, table: Any, columns: Iterable[str]) -> None:
    """Check that the DataFrame ``table`` has every column in ``columns``."""
    if not hasattr(table, "columns"):
        raise TypeError(f"Expected `{name}` to be a pandas DataFrame, got {_describe(table)}.")
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise ValueError(f"`{name}` is missing column(s) {', '.join(missing)}.")


def check_shape2(name: str, value: Any) -> tuple[int, int]:
    """Return ``value`` as (rows, columns) of positive ints, or raise naming ``name``."""
    if not isinstance(value, tuple | list) or len(value) != 2:
        raise ValueError(f"Expected `{name}` to be (rows, columns), got {value!r}.")
    return tuple(check_int(name, v, minimum=1) for v in value)  # type: ignore[return-value]

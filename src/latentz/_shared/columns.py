"""Columns set on a table at once.

Each column inserted into a pandas table one at a time rebuilds its column index, and the next
lookup rebuilds the index's hash table: on a small table that costs more than the arithmetic that
made the column. :func:`with_columns` joins all of them in one step.
"""

from __future__ import annotations

import copy

import numpy as np
import pandas as pd

__all__ = ["with_columns"]


def with_columns(table: pd.DataFrame, new: dict[str, np.ndarray]) -> pd.DataFrame:
    """A copy of ``table`` with the ``new`` columns (name → array of ``len(table)`` values) set:
    those it already has replaced where they stand, the others appended in ``new``'s order; its
    index and ``attrs`` kept."""
    replaced = [name for name in new if name in table.columns]
    kept = table.drop(columns=replaced) if replaced else table
    out = pd.concat([kept, pd.DataFrame(new, index=table.index)], axis=1)
    if replaced:  # the replaced columns back where they stood
        out = out[[*table.columns, *(name for name in new if name not in table.columns)]]
    out.attrs = copy.deepcopy(table.attrs)
    return out

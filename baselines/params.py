"""The checks every plug-in factory of this package makes on its keyword arguments."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import numpy as np

__all__ = ["params_from", "positive_vector"]


def params_from(cls: type, kwargs: dict[str, Any], what: str) -> Any:
    """``cls(**kwargs)``, after refusing unknown names with one message naming them and the valid
    ones (``what`` says whose: e.g. "controller gain", "CBF filter parameter"). The dataclass's own
    ``__post_init__`` then checks each value's range by field."""
    valid = {f.name for f in fields(cls)}
    unknown = set(kwargs) - valid
    if unknown:
        raise ValueError(f"unknown {what}(s) {sorted(unknown)}; valid: {sorted(valid)}")
    return cls(**kwargs)


def positive_vector(owner: str, name: str, value: Any, n: int, one_for_all: bool = False) -> tuple[float, ...]:
    """A per-joint gain as a tuple of ``n`` finite floats > 0, or ValueError naming ``owner.name``;
    with ``one_for_all`` a single number stands for every joint."""
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if one_for_all and arr.size == 1:
        arr = np.full(n, float(arr[0]))
    if arr.shape != (n,):
        what = f"one number or {n}" if one_for_all else f"{n} entries"
        raise ValueError(f"{owner}.{name} must have {what} (one per joint), got shape {arr.shape}")
    if not np.all(np.isfinite(arr) & (arr > 0)):
        raise ValueError(f"{owner}.{name} entries must be finite and > 0, got {arr.tolist()}")
    return tuple(float(v) for v in arr)

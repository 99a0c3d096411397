"""The checks every plug-in factory of this package makes on its keyword arguments."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import numpy as np

from blf_gym.model.params import ArmParams

__all__ = ["PAPER_LINKS", "params_from", "positive_vector"]

PAPER_LINKS = ArmParams().n_links
"""Links of the paper's arm (Table 1, the default :class:`~blf_gym.model.params.ArmParams`): the length
of every default gain vector that is the paper's or was tuned on its arm. An arm of another number of
links is given its gains (:func:`positive_vector` says so by name)."""


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
    with ``one_for_all`` a single number stands for every joint. A vector of :data:`PAPER_LINKS`
    entries (a default for the paper's arm) on an arm of other than that many links is refused with
    a message that says the gain must be given for that arm."""
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if one_for_all and arr.size == 1:
        arr = np.full(n, float(arr[0]))
    if arr.shape != (n,):
        what = f"one number or {n} entries" if one_for_all else f"{n} entries"
        hint = ""
        if arr.shape == (PAPER_LINKS,):
            hint = (f"; {PAPER_LINKS} entries fit the paper's {PAPER_LINKS}-link arm, whose gains are the defaults: "
                    f"give {name} for this arm of {n}")
        raise ValueError(f"{owner}.{name} must have {what} (one per joint), got shape {arr.shape}{hint}")
    if not np.all(np.isfinite(arr) & (arr > 0)):
        raise ValueError(f"{owner}.{name} entries must be finite and > 0, got {arr.tolist()}")
    return tuple(float(v) for v in arr)

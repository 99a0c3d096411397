"""The one check every plug-in factory of this package makes on its keyword arguments."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

__all__ = ["params_from"]


def params_from(cls: type, kwargs: dict[str, Any], what: str) -> Any:
    """``cls(**kwargs)``, after refusing unknown names with one message naming them and the valid
    ones (``what`` says whose: e.g. "controller gain", "CBF filter parameter"). The dataclass's own
    ``__post_init__`` then checks each value's range by field."""
    valid = {f.name for f in fields(cls)}
    unknown = set(kwargs) - valid
    if unknown:
        raise ValueError(f"unknown {what}(s) {sorted(unknown)}; valid: {sorted(valid)}")
    return cls(**kwargs)

"""The checks every plug-in factory of this package makes on its keyword arguments."""

from __future__ import annotations

from dataclasses import fields
from functools import lru_cache
from typing import Any

import numpy as np

from blf_gym.model.dynamics import mass_matrix
from blf_gym.model.params import ArmParams

__all__ = ["PAPER_LINKS", "params_from", "positive_vector", "by_position", "fastest_pole", "velocity_gain"]

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
                    f"give {name} for this arm of {n}, or leave it out where the law carries its defaults to "
                    "the arm (docs/family.md)")
        raise ValueError(f"{owner}.{name} must have {what} (one per joint), got shape {arr.shape}{hint}")
    if not np.all(np.isfinite(arr) & (arr > 0)):
        raise ValueError(f"{owner}.{name} entries must be finite and > 0, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


# ---- the paper's gains on an arm of another number of links (docs/family.md, "Gains") -----------
# The paper's gain vectors are for its 3 joints: base, elbow, wrist. On an arm of n joints, joint j
# sits at position j / (n - 1) along the chain (0: the base, 1: the last joint), as the paper's
# joints sit at 0, 1/2 and 1; a gain's shape is read off the paper's vector at that position
# (straight lines between the paper's joints). A gain that acts as a bandwidth (1/s: K1) is read as
# it is. A gain that turns a velocity error into a torque (N m s/rad: K2) makes, through the arm's
# inertia, the velocity loop's poles: the eigenvalues of M(q)^-1 K2, fastest where the arm is
# lightest. On the paper's arm the fastest over all poses is about 2.0e4 1/s (h = 0.1 ms puts h times
# it at 2.0, inside ODE3's stability limit of about 2.5 on the real axis); the shape is scaled by one
# number so that the new arm's fastest pole over the poses is the paper's. Read as a rate per joint instead (K2 / M_jj),
# the gains ignored the coupling between joints and made every other member's loop unstable at
# 0.1 ms.

_POSES = 512
"""Poses the fastest pole is taken over: joint angles drawn uniformly in [-pi, pi) (seed 0)."""


def _positions(n: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)


def by_position(values: Any, n: int) -> tuple[float, ...]:
    """A per-joint gain of the paper's arm (:data:`PAPER_LINKS` entries) read at the positions of
    ``n`` joints; ``values`` itself at n = :data:`PAPER_LINKS`."""
    values = tuple(float(v) for v in values)
    if n == PAPER_LINKS:
        return values
    return tuple(float(v) for v in np.interp(_positions(n), _positions(PAPER_LINKS), values))


def fastest_pole(gains: Any, arm: ArmParams) -> float:
    """The largest real part of the eigenvalues of M(q)^-1 diag(gains) over :data:`_POSES` poses
    of ``arm`` (and the straight arm), 1/s: the velocity loop's fastest pole."""
    K = np.diag(np.asarray(gains, dtype=float))
    qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (_POSES, arm.n_links))
    qs[0] = 0.0
    return float(max(np.linalg.eigvals(np.linalg.solve(mass_matrix(q, arm), K)).real.max() for q in qs))


def velocity_gain(values: Any, arm: ArmParams) -> tuple[float, ...]:
    """A per-joint torque gain of the paper's arm (N m s/rad, such as K2) for ``arm``: its shape
    read at the new joints' positions (:func:`by_position`), scaled so that :func:`fastest_pole`
    on ``arm`` is the paper's gains' on the paper's arm; ``values`` itself on an arm of
    :data:`PAPER_LINKS` links."""
    return _velocity_gain(tuple(float(v) for v in values), arm)


@lru_cache(maxsize=64)
def _velocity_gain(values: tuple[float, ...], arm: ArmParams) -> tuple[float, ...]:
    n = arm.n_links
    if n == PAPER_LINKS:
        return values
    shape = np.asarray(by_position(values, n))
    scale = fastest_pole(values, ArmParams()) / fastest_pole(shape, arm)
    return tuple(float(v) for v in shape * scale)

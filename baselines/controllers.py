"""The paper's laws and observer packaged as blf_gym plug-ins, with their gains (Table 2).

``bc``, ``lesobc``, ``proposed`` and ``leso`` are the factories registered under the entry-point
groups ``blf_gym.controllers`` and ``blf_gym.observers``; keyword arguments override gains, e.g.
``proposed(K2=(45, 45, 15), barrier_clip=0.9)``. The default gain vectors are the paper's, for its
3-link arm; a law for an arm of n links is built with that arm as ``nominal``, its defaults carried
to that arm by docs/family.md's rule (:func:`controller_gains`), or with its gains given, one number
for every joint or n of them: ``proposed(nominal=arm, K1=20.0, K2=(45.0, 15.0))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blf_gym.plugins.blocks import Controller, Observer
from blf_gym.model.family import family_arm
from blf_gym.model.params import ArmParams

from .cbf import cbf_filter
from .filters import barrier_filter
from .laws import bc_output, lesobc_output, proposed_output
from .leso import leso_rhs
from .params import PAPER_LINKS, by_position, velocity_gain, params_from, positive_vector

__all__ = ["ControllerGains", "ObserverGains", "PROPOSED_TUNED", "PROPOSED_TUNED_MEMBER_GAINS", "controller_gains",
           "member_defaults", "bc", "lesobc", "proposed", "proposed_tuned", "leso"]


@dataclass(frozen=True)
class ControllerGains:
    """Backstepping gains (paper Table 2) and the barrier guard. K1 and K2 are one number for every
    joint or one per joint; their defaults are the paper's, for its 3-link arm: built directly on an
    arm of other than 3 links (``nominal``) it must be given both (ValueError naming the gain
    otherwise); the laws' factories carry the defaults to that arm (:func:`controller_gains`)."""

    # paper: Table 2's diagonals, for the paper's 3-link arm
    K1: tuple[float, ...] = field(default=(20.0, 20.0, 15.0), metadata={"unit": "1/s"})
    """Diagonal of K1 = 10 diag(2, 2, 1.5), 1/s (each > 0; one number: the same on every joint)."""
    K2: tuple[float, ...] = field(default=(45.0, 45.0, 15.0), metadata={"unit": "N m s/rad"})
    """Diagonal of K2 = 30 diag(1.5, 1.5, 0.5), N m s/rad (each > 0; one number: the same on every joint)."""
    barrier_clip: float = field(default=0.95, metadata={"unit": "-"})
    """rho in (0, 1): the barrier term is evaluated with |e1| <= rho x bound. 0.95 keeps the
    closed loop integrable at h = 0.1 ms (docs/model.md section 5); raise it only with a smaller step."""
    nominal: ArmParams = field(default_factory=ArmParams)
    """The controller's model of the arm (paper Table 1)."""

    def __post_init__(self) -> None:
        n = self.nominal.n_links
        object.__setattr__(self, "K1", positive_vector("ControllerGains", "K1", self.K1, n, one_for_all=True))
        object.__setattr__(self, "K2", positive_vector("ControllerGains", "K2", self.K2, n, one_for_all=True))
        if not (math.isfinite(self.barrier_clip) and 0.0 < self.barrier_clip < 1.0):
            raise ValueError(f"ControllerGains.barrier_clip must be in (0, 1), got {self.barrier_clip!r}")


@dataclass(frozen=True)
class ObserverGains:
    """LESO bandwidth (paper Table 2)."""

    k0: float = field(default=200.0, metadata={"unit": "1/s"})
    """Observer bandwidth: all three poles per joint at -k0, 1/s (> 0)."""
    nominal: ArmParams = field(default_factory=ArmParams)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.k0) and self.k0 > 0):
            raise ValueError(f"ObserverGains.k0 must be a finite number > 0, got {self.k0!r}")


def controller_gains(kwargs: dict[str, Any], defaults: dict[str, Any] | None = None) -> ControllerGains:
    """:class:`ControllerGains` from keyword overrides (``kwargs``) over a law's own defaults
    (``defaults``, gains for the paper's arm; :class:`ControllerGains`' where absent), refusing
    unknown names by name. On a ``nominal`` arm of other than the paper's 3 links, the defaults'
    K1 and K2 are carried to that arm by the rule of docs/family.md ("Gains": K1 read at the
    joints' positions along the chain, K2's shape too, scaled to the paper's fastest velocity pole); gains given in ``kwargs`` are taken
    as they are (a vector for 3 joints on another arm is refused by name)."""
    base = {"K1": ControllerGains.K1, "K2": ControllerGains.K2, **(defaults or {})}
    nominal = kwargs.get("nominal")
    if isinstance(nominal, ArmParams) and nominal.n_links != PAPER_LINKS:
        # a default for the paper's 3 joints is carried; one already for this arm is kept
        if np.size(base["K1"]) == PAPER_LINKS:
            base["K1"] = by_position(np.broadcast_to(base["K1"], (PAPER_LINKS,)), nominal.n_links)
        if np.size(base["K2"]) == PAPER_LINKS:
            base["K2"] = velocity_gain(np.broadcast_to(base["K2"], (PAPER_LINKS,)), nominal)
    return params_from(ControllerGains, {**base, **kwargs}, "controller gain")


def member_defaults(nominal: Any, chosen: dict[int, dict[str, float]], defaults: dict[str, Any]) -> dict[str, Any]:
    """A law's defaults on ``nominal``: on a member of the task family (its own arm, of n links) whose
    gains a search chose (``chosen[n]``, each gain the first entry of its vector, as
    ``python -m baselines.gains LAW --n-links N`` states it), the vectors :func:`controller_gains`
    carries to that arm scaled to those first entries; on any other arm ``defaults`` (the paper arm's),
    which :func:`controller_gains` carries by the rule."""
    n = getattr(nominal, "n_links", None)
    if n not in chosen or nominal != family_arm(n):
        return defaults
    carried = controller_gains({"nominal": nominal}, defaults)
    return {k: tuple(v * x / getattr(carried, k)[0] for x in getattr(carried, k)) for k, v in chosen[n].items()}


_LESO_STATES = {"x1_hat": "n", "x2_hat": "n", "x3_hat": "n"}
"""The LESO's states: estimated angles (rad), velocities (rad/s) and lumped disturbance (rad/s^2)."""


def bc(**kwargs: Any) -> Controller:
    """Backstepping control (full state: reads the true velocity)."""
    return Controller("bc", bc_output, controller_gains(kwargs))


def lesobc(**kwargs: Any) -> Controller:
    """Backstepping with the LESO's velocity and disturbance estimates."""
    return Controller("lesobc", lesobc_output, controller_gains(kwargs),
                      outputs={"u_law": "n", "z1": "n", "z2_hat": "n"})


def proposed(**kwargs: Any) -> Controller:
    """The paper's LESO + barrier-Lyapunov law; publishes z1 (rad), z2_hat = x2_hat - alpha1 (rad/s)
    and its barrier term (1/rad)."""
    return Controller("proposed", proposed_output, controller_gains(kwargs),
                      outputs={"u_law": "n", "z1": "n", "z2_hat": "n", "barrier": "n"},
                      filters={"barrier": barrier_filter, "cbf": cbf_filter})


PROPOSED_TUNED = {"K1": (1280.0, 1280.0, 960.0), "K2": (11.25, 11.25, 3.75)}  # paper: tuned on its 3-link arm
"""The proposed law's gains chosen by the grid search that chose PPC's (docs/gains/proposed: K1 = 1280
and K2 = 11.25 in the grid's scaling of the paper's vectors, the best of 40 points on the same 10
selection episodes within the same torque budget, 1.25 times the paper-gain law's RMS torque). Chosen
on the paper's 3-link arm; on an arm of another number of links they are carried to it by
docs/family.md's rule unless K1 and K2 are given."""


PROPOSED_TUNED_MEMBER_GAINS: dict[int, dict[str, float]] = {  # chosen by the searches named below
    2: {"K1": 1280.0, "K2": 12.390671665762405},
    4: {"K1": 1280.0, "K2": 26.942644011767488},
    5: {"K1": 1280.0, "K2": 22.128259433048658},
    6: {"K1": 2560.0, "K2": 20.503601833576987},
    7: {"K1": 2560.0, "K2": 19.092879177475517}}
"""The tuned law's gains on the task family's other members (docs/family.md, "Gains"), chosen per
member by the search that chose :data:`PROPOSED_TUNED` (``docs/gains/family/run.sh proposed``: the
same 40-point grid carried, on the member's presets and training-suite seeds 0-7 only, under the same
torque budget; docs/gains/family/proposed_n<N>), each the first entry of a vector of the carried
shape. Another arm takes :data:`PROPOSED_TUNED` carried by the rule."""


def proposed_tuned(**kwargs: Any) -> Controller:
    """The paper's law with tuned gains (:data:`PROPOSED_TUNED`, and on a member of the task family
    :data:`PROPOSED_TUNED_MEMBER_GAINS`); everything else, the barrier and its filters included, is
    the proposed law's."""
    defaults = member_defaults(kwargs.get("nominal"), PROPOSED_TUNED_MEMBER_GAINS, PROPOSED_TUNED)
    return Controller("proposed_tuned", proposed_output, controller_gains(kwargs, defaults),
                      outputs={"u_law": "n", "z1": "n", "z2_hat": "n", "barrier": "n"},
                      filters={"barrier": barrier_filter, "cbf": cbf_filter})


def leso(**kwargs: Any) -> Observer:
    """The linear extended state observer, x_hat(0) = [q(0), 0, 0]."""
    return Observer("leso", leso_rhs, _LESO_STATES, params_from(ObserverGains, kwargs, "observer gain"))

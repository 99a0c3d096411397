"""Where controllers and observers come from: the registry over the entry-point groups.

``blf_gym`` never imports a controller. Plug-ins are :class:`~blf_gym.plugins.blocks.Controller` and
:class:`~blf_gym.plugins.blocks.Observer` blocks (the protocol is in :mod:`blf_gym.plugins.blocks` and
docs/extending.md). Named ones are found through the entry-point groups ``blf_gym.controllers``
and ``blf_gym.observers``: each entry point is a factory whose keyword arguments override the
plug-in's parameters. The ``baselines`` package registers ``bc``, ``lesobc``, ``proposed`` and
``leso``, so the dependency points from ``baselines`` to ``blf_gym`` only; an installed package of
yours registers its own the same way, and every command and ``gym.make`` then accept its names.
``none`` (no inner law, plain RL) is built in.

Whole policies that act on the plain env from its observation (a model-predictive controller, say)
are found the same way, in the group ``blf_gym.policies``: each entry point is a factory of an
object with SB3's ``predict(observation, state, episode_start, deterministic)`` and an
``env_kwargs`` dict, the arguments of the env it acts in (``blf-eval --policies NAME`` scores one).
"""

from __future__ import annotations

from importlib.metadata import entry_points
from typing import Any

from blf_gym.plugins.blocks import (
    NO_CONTROLLER,
    Controller,
    Observer,
    model_length,
    nominal_length,
    nominal_model_into,
    work_length,
)

__all__ = [
    "Controller",
    "Observer",
    "NO_CONTROLLER",
    "model_length",
    "nominal_length",
    "nominal_model_into",
    "work_length",
    "make_controller",
    "make_observer",
    "available_controllers",
    "available_observers",
    "available_policies",
    "make_policy",
]


def _group(name: str) -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=name)}


def available_controllers() -> list[str]:
    """Names accepted by :func:`make_controller` (``none`` plus the registered plug-ins)."""
    return ["none", *sorted(_group("blf_gym.controllers"))]


def available_observers() -> list[str]:
    """Names accepted by :func:`make_observer` (the registered plug-ins)."""
    return sorted(_group("blf_gym.observers"))


def _factory(group: str, kind: str, spec: Any, names: Any, tail: str) -> Any:
    """The factory registered as ``spec`` in the entry-point group ``group``; ValueError naming the
    accepted names (``names()``, then ``tail``) when there is none, or naming the entry point that
    fails to load."""
    eps = _group(group)
    if spec not in eps:
        raise ValueError(f"unknown {kind} {spec!r}; accepted values: {names()} {tail}")
    try:
        return eps[spec].load()
    except Exception as exc:  # noqa: BLE001 (a broken plug-in package, reported by name)
        raise ValueError(f"{kind} {spec!r}: its entry point {eps[spec].value} failed to load: "
                         f"{type(exc).__name__}: {exc}") from exc


def _load(group: str, kind: str, cls: type, spec: Any, kwargs: dict[str, Any]) -> Any:
    names = available_controllers if cls is Controller else available_observers
    factory = _factory(group, kind, spec, names, f"(or a blf_gym.plugins.blocks.{cls.__name__} object). If the paper's "
                       "are missing, install the project (pip install -e .) so its entry points are registered.")
    obj = factory(**kwargs)
    if not isinstance(obj, cls):
        raise ValueError(f"entry point {spec!r} of {group} returned {type(obj).__name__}, not a "
                         f"blf_gym.plugins.blocks.{cls.__name__}")
    return obj


def make_controller(spec: "str | Controller", **kwargs: Any) -> Controller:
    """A :class:`~blf_gym.plugins.blocks.Controller` from a registered name (``bc``, ``lesobc``,
    ``proposed``, ``none``, or an installed plug-in's) or an existing object. ``kwargs`` go to the
    plug-in's factory (e.g. gains)."""
    if isinstance(spec, Controller):
        if kwargs:
            raise ValueError("keyword arguments only apply when the controller is given by name")
        return spec
    if spec == "none":
        if kwargs:
            raise ValueError("controller 'none' takes no parameters")
        return NO_CONTROLLER
    return _load("blf_gym.controllers", "controller", Controller, spec, kwargs)


def make_observer(spec: "str | Observer" = "leso", **kwargs: Any) -> Observer:
    """An :class:`~blf_gym.plugins.blocks.Observer` from a registered name (``leso``, or an installed
    plug-in's) or an existing object."""
    if isinstance(spec, Observer):
        if kwargs:
            raise ValueError("keyword arguments only apply when the observer is given by name")
        return spec
    return _load("blf_gym.observers", "observer", Observer, spec, kwargs)


def available_policies() -> list[str]:
    """Names accepted by :func:`make_policy` (the ``blf_gym.policies`` entry points)."""
    return sorted(_group("blf_gym.policies"))


def make_policy(name: str, **kwargs: Any) -> Any:
    """A registered policy (``blf_gym.policies``) built by its factory with ``kwargs``: an object
    with SB3's ``predict`` and ``env_kwargs``, the env arguments it must be scored with (for
    ``gym.make("PlanarBLF-v0", **policy.env_kwargs)``)."""
    factory = _factory("blf_gym.policies", "policy", name, available_policies,
                       "(the blf_gym.policies entry points; reinstall the project if this list is empty)")
    obj = factory(**kwargs)
    if not callable(getattr(obj, "predict", None)) or not isinstance(getattr(obj, "env_kwargs", None), dict):
        raise ValueError(f"entry point {name!r} of blf_gym.policies returned {type(obj).__name__}, which lacks "
                         "predict(observation, state, episode_start, deterministic) or an env_kwargs dict")
    return obj

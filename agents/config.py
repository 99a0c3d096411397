"""One typed configuration for training, shared by ``blf-train``, ``blf-sweep`` and ``blf-tune``.

Two parts, each declared once here:

* :class:`RunSpec`: what a run is (algorithm, mode, inner law, observer, scenario, budget, seeds),
  given on ``blf-train``'s command line or in a sweep file's top-level keys;
  :meth:`RunSpec.checked` validates it the same way for both.
* :class:`TrainConfig`: how it trains, the keys of a config YAML (``agents/configs/*.yaml``).
  :func:`check_config` refuses an unknown key or a value of the wrong type, naming the file and
  the key. The ``env`` keys are the env's own arguments (:func:`env_keys`, read from
  ``blf_gym.envs.envcore.EnvCore``'s signature), less the ones a run sets itself.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from blf_gym import ENV_IDS
from blf_gym.model.params import check_int, check_real, is_integer

__all__ = ["RunSpec", "TrainConfig", "CONFIG_DIR", "CONFIG_KEYS", "RUN_SET_ENV_KEYS", "SET_HELP", "add_config_options",
           "apply_overrides", "check_config", "curriculum_scale", "env_keys", "parse_overrides", "set_dotted", "shipped_config"]

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
"""The shipped training configs, ``<algo>_<env id>.yaml``."""


def shipped_config(algo: str, mode: str) -> Path | None:
    """The config ``blf-train`` and a sweep use for ``algo`` in ``mode`` when none is given:
    ``CONFIG_DIR/<algo>_<env id>.yaml``, or None when none ships (an algorithm registered by another
    package), in which case :class:`TrainConfig`'s defaults and the algorithm's own
    hyperparameters apply."""
    path = CONFIG_DIR / f"{algo}_{ENV_IDS[mode]}.yaml"
    return path if path.is_file() else None


@dataclass(frozen=True)
class TrainConfig:
    """The keys of a training config file, with their types and the defaults ``blf-train`` uses
    for keys a file leaves out."""

    policy: str = field(default="MlpPolicy", metadata={"kind": "str"})
    """The SB3 policy class name."""
    n_envs: int = field(default=1, metadata={"kind": "count"})
    """Parallel arms of the training env (>= 1)."""
    normalize: bool = field(default=False, metadata={"kind": "bool"})
    """Observation normalization (SB3's VecNormalize), recorded in the agent's metadata."""
    normalize_reward: bool = field(default=False, metadata={"kind": "bool"})
    """Reward normalization too (needs ``normalize: true``)."""
    env: Mapping[str, Any] = field(default_factory=dict, metadata={"kind": "env"})
    """Env keyword arguments (:func:`env_keys`), checked again by the env itself."""
    hyperparams: Mapping[str, Any] = field(default_factory=dict, metadata={"kind": "mapping"})
    """Keyword arguments of the algorithm's constructor (``lin_<x>`` for a linear decay)."""
    policy_kwargs: Mapping[str, Any] = field(default_factory=dict, metadata={"kind": "mapping"})
    """The policy's keyword arguments (``net_arch``, ``log_std_init``, ...)."""
    action_noise_std: float | None = field(default=None, metadata={"kind": "nonneg"})
    """Gaussian exploration noise of off-policy algorithms, in action units (>= 0)."""
    curriculum: Mapping[str, Any] = field(default_factory=dict, metadata={"kind": "mapping"})
    """A funnel-width curriculum (:func:`curriculum_scale`): ``{bound_scale: S, until: T}`` trains
    the first episodes with bounds S times as wide (1 < S <= ``blf_gym.envs.envcore.MAX_BOUND_SCALE``) and shrinks them geometrically to
    the benchmark's own by agent step T (>= 1), and at 1 from then on; empty (the default): none.
    Learning curves and blf-eval always score at the benchmark's bounds."""
    init_from: str = field(default="", metadata={"kind": "str"})
    """A warm start: the run folder (or model zip) of a trained agent of the same mode whose policy
    (every weight, ``log_std`` included) and observation statistics a new run starts from; empty
    (the default): none. Other state (optimizer, reward statistics, a cost critic) starts fresh."""
    eval_freq: int = field(default=20_000, metadata={"kind": "count"})
    """Agent steps between two learning-curve points (>= 1)."""
    curve_suite_seeds: int = field(default=4, metadata={"kind": "count"})
    """Held-out training-suite episodes of each learning-curve point (>= 1)."""
    checkpoint_freq: int = field(default=10_000, metadata={"kind": "count"})
    """Agent steps between two checkpoints (>= 1)."""
    note: str = field(default="", metadata={"kind": "str"})
    """Free text, recorded with the run."""

    @classmethod
    def of(cls, cfg: Mapping[str, Any], where: str) -> "TrainConfig":
        """The typed config of a mapping (a YAML file's, with any ``--set``): checked by
        :func:`check_config`, keys left out or null taking the defaults; ValueError naming ``where``
        and the key otherwise."""
        check_config(cfg, where)
        tc = cls(**{k: v for k, v in cfg.items() if v is not None})
        if tc.normalize_reward and not tc.normalize:
            raise ValueError(f"{where}: normalize_reward needs normalize: true")
        if tc.curriculum:
            _check_curriculum(tc.curriculum, where)
        return tc


def _check_curriculum(cur: Mapping[str, Any], where: str) -> None:
    from blf_gym.envs.envcore import MAX_BOUND_SCALE

    if set(cur) != {"bound_scale", "until"}:
        raise ValueError(f"{where}: curriculum takes exactly bound_scale and until, got {sorted(cur)}")
    check_real(f"{where}: curriculum", "bound_scale", cur["bound_scale"], lo=1.0, hi=MAX_BOUND_SCALE,
               lo_open=True, hint=" (the funnel's width at the start, in multiples of the benchmark's)")
    check_int(f"{where}: curriculum", "until", cur["until"], lo=1,
              hint=" (the agent step by which the bounds are the benchmark's)")


def curriculum_scale(cur: Mapping[str, Any], steps: int) -> float:
    """The funnel's width factor at agent step ``steps`` of a curriculum ``{bound_scale: S,
    until: T}``: ``S ** (1 - steps / T)`` before T (geometric: each stretch of T/10 steps narrows it
    by the same ratio), exactly 1 from T on; 1 without a curriculum."""
    if not cur or steps >= cur["until"]:
        return 1.0
    return float(cur["bound_scale"]) ** (1.0 - steps / float(cur["until"]))


CONFIG_KEYS = tuple(f.name for f in dataclasses.fields(TrainConfig))
"""The keys a training config may hold (the fields of :class:`TrainConfig`)."""

RUN_SET_ENV_KEYS = ("num_envs", "scenario", "controller", "observer", "threads", "single", "record",
                    "record_channels")
"""EnvCore's arguments that a training run sets itself (from its command line or its sweep), never
from a config's ``env``."""

_KINDS = {f.name: f.metadata["kind"] for f in dataclasses.fields(TrainConfig)}


def env_keys() -> tuple[str, ...]:
    """The keys a config's ``env`` may hold: ``EnvCore``'s keyword arguments less
    :data:`RUN_SET_ENV_KEYS`."""
    import inspect

    from blf_gym.envs.envcore import EnvCore

    return tuple(p for p in inspect.signature(EnvCore.__init__).parameters
                 if p != "self" and p not in RUN_SET_ENV_KEYS)



def _type_error(where: str, key: str, want: str, v: Any) -> ValueError:
    return ValueError(f"{where}: {key} must be {want}, got {v!r}")


def check_config(cfg: Any, where: str) -> None:
    """Check a config mapping against :class:`TrainConfig`: every key known, every value of its
    type; ValueError naming ``where`` and the key otherwise. A key set to null counts as left out."""
    if not isinstance(cfg, Mapping):
        raise ValueError(f"{where}: a config is a mapping of {list(CONFIG_KEYS)}, got {cfg!r}")
    unknown = sorted(set(cfg) - set(CONFIG_KEYS), key=str)
    if unknown:
        raise ValueError(f"{where}: unknown config key(s) {unknown}; accepted: {list(CONFIG_KEYS)}")
    for key, v in cfg.items():
        kind = _KINDS[key]
        if v is None:
            continue
        if kind == "str" and not isinstance(v, str):
            raise _type_error(where, key, "a string", v)
        if kind == "bool" and not isinstance(v, bool):
            raise _type_error(where, key, "true or false", v)
        if kind == "count" and not (is_integer(v) and v >= 1):
            raise _type_error(where, key, "an integer >= 1", v)
        if kind == "nonneg" and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                     and math.isfinite(v) and v >= 0):
            raise _type_error(where, key, "a finite number >= 0", v)
        if kind in ("mapping", "env"):
            if not isinstance(v, Mapping) or not all(isinstance(k, str) for k in v):
                raise _type_error(where, key, "a mapping with string keys", v)
        if kind == "env":
            allowed = env_keys()
            bad = sorted(set(v) - set(allowed))
            if bad:
                raise ValueError(f"{where}: unknown env key(s) {bad}; accepted: {list(allowed)}"
                                 + (f" ({', '.join(b for b in bad if b in RUN_SET_ENV_KEYS)} is set by the "
                                    f"run itself, not by a config)" if set(bad) & set(RUN_SET_ENV_KEYS) else ""))


SET_HELP = ("override one key of the training config, KEY=VALUE (repeatable): a key of "
            "agents.config.TrainConfig, or env.KEY, hyperparams.KEY or policy_kwargs.KEY; VALUE is read as "
            "YAML (1e-4, true, [64, 64], null) (default: none, the file's values)")
"""The help of ``--set``, which blf-train, blf-sweep and blf-tune share."""

_FLOAT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")
_NESTED = tuple(f.name for f in dataclasses.fields(TrainConfig) if _KINDS[f.name] in ("mapping", "env"))


def set_dotted(cfg: dict[str, Any], key: str, value: Any) -> None:
    """Set ``cfg[key]``, or ``cfg[head][sub]`` for a dotted ``head.sub``, in place."""
    import copy

    parts = key.split(".")
    node = cfg
    for p in parts[:-1]:
        if node.get(p) is None:
            node[p] = {}
        node = node[p]
    node[parts[-1]] = copy.deepcopy(value)


def parse_overrides(sets: Sequence[str], where: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` items (see :data:`SET_HELP`) as {dotted key: value}; ValueError naming the item
    when it is malformed or names no config key."""
    import yaml

    out: dict[str, Any] = {}
    for item in sets:
        key, eq, text = str(item).partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"{where} {item!r}: expected KEY=VALUE (e.g. n_envs=8, env.control_period=0.02, "
                             "hyperparams.learning_rate=1e-4)")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{where} {item!r}: the value is not valid YAML ({exc})") from None
        if isinstance(value, str) and _FLOAT.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-4 (no dot) as a string; a command line means the number
        head, dot, sub = key.partition(".")
        if head not in CONFIG_KEYS:
            raise ValueError(f"{where} {item!r}: unknown config key {head!r}; accepted: {list(CONFIG_KEYS)}")
        if dot and (head not in _NESTED or not sub or "." in sub):
            raise ValueError(f"{where} {item!r}: only {', '.join(_NESTED)} take a sub-key (KEY.SUB=VALUE)")
        out[key] = value
    return out


def apply_overrides(cfg: Mapping[str, Any], overrides: Mapping[str, Any], where: str) -> dict[str, Any]:
    """A copy of ``cfg`` with the dotted ``overrides`` set, checked by :func:`check_config` (``where``
    names it in errors)."""
    import copy

    out = copy.deepcopy(dict(cfg))
    for key, value in overrides.items():
        set_dotted(out, key, value)
    check_config(out, where)
    return out


def add_config_options(parser: Any) -> None:
    """``--set KEY=VALUE`` (into ``args.overrides``): the training config from the command line, the
    same in blf-train, blf-sweep and blf-tune."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help=SET_HELP)


@dataclass(frozen=True)
class RunSpec:
    """What a training run is. ``controller`` None means the proposed law in residual mode (plain
    mode has no inner law, so it must stay None there)."""

    algo: str
    mode: str
    controller: str | None
    observer: str
    scenario: str
    timesteps: int
    seeds: Sequence[int]

    def checked(self) -> "RunSpec":
        """This spec with the defaults filled in (``controller``), or ValueError naming the field
        and its accepted values. The held-out suites (stress, certificate) are refused."""
        from blf_gym.plugins.registry import available_controllers, available_observers
        from blf_gym.envs.scenarios import HELD_OUT_SUITES, resolve_scenario

        from .loading import available_algorithms

        if self.algo not in available_algorithms():
            raise ValueError(f"unknown algo {self.algo!r}; accepted: {available_algorithms()}")
        if self.mode not in ENV_IDS:
            raise ValueError(f"unknown mode {self.mode!r}; accepted: {list(ENV_IDS)}")
        if self.mode == "plain" and self.controller is not None:
            raise ValueError("controller applies to mode: residual only (plain mode has no inner law)")
        controller = self.controller or ("proposed" if self.mode == "residual" else None)
        if controller is not None and controller not in available_controllers():
            raise ValueError(f"unknown controller {controller!r}; accepted: {available_controllers()}")
        if self.observer not in available_observers():
            raise ValueError(f"unknown observer {self.observer!r}; accepted: {available_observers()}")
        if self.scenario in HELD_OUT_SUITES:
            raise ValueError(f"the {self.scenario} suite is held out: no training, tuning, seed choice or early "
                             f"stopping may read it (blf-eval --suite {self.scenario} scores on it); train on "
                             "randomized or a preset")
        resolve_scenario(self.scenario)
        if not (is_integer(self.timesteps) and self.timesteps >= 1):
            raise ValueError(f"timesteps must be an integer >= 1, got {self.timesteps!r}")
        seeds = list(self.seeds) if isinstance(self.seeds, (list, tuple)) else None
        if not seeds or not all(is_integer(s) and s >= 0 for s in seeds) or len(set(seeds)) != len(seeds):
            if isinstance(self.seeds, (list, tuple)) and len(self.seeds) == 1:
                raise ValueError(f"seed must be an integer >= 0, got {self.seeds[0]!r}")
            raise ValueError(f"seeds must be a non-empty list of distinct integers >= 0, got {self.seeds!r}")
        return dataclasses.replace(self, controller=controller)

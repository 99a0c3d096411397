"""``PlanarBLF-v0``: the Gymnasium environment."""

from __future__ import annotations

import textwrap
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from blf_gym.envs.envcore import (ARGUMENTS, CORE_BOUND_SCALE, INFO_KEYS, EnvCore, check_env_kwargs, observation_layout,
                      warn_if_oversubscribed)
from blf_gym.model.params import Scenario, check_int

__all__ = ["PlanarBLFEnv", "MAX_FPS", "make_env", "make_residual_env", "check_residual_controller"]

# the fastest video rate: the default control rate (100 Hz). MP4 (H.264) holds it and players
# keep its duration (a 60 Hz display drops frames, not time); faster control periods are
# subsampled to it
MAX_FPS = 100.0


def _rows(header: tuple[str, ...], rows: list[tuple[Any, ...]], indent: str = "") -> str:
    """A Markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |" for r in rows]
    return "\n".join(indent + line for line in out)


def _default_links() -> int:
    """Links of the default scenario's arm (the paper's: 3), which the docstring's tables show."""
    from blf_gym.model.params import preset

    return preset(_defaults()["scenario"]).arm.n_links


def observation_table(privileged: bool = True, indent: str = "", n: int | None = None) -> str:
    """The default observation's entries (index, name, unit, box), a Markdown table made from
    :data:`blf_gym.envs.observation.OBSERVATION` for an arm of ``n`` links (default: the default
    scenario's, the paper's 3-link arm)."""
    n = _default_links() if n is None else n
    rows = [(i, name, unit, f"{lo:g}", f"{hi:g}") for i, (name, unit, lo, hi)
            in enumerate(observation_layout(n, privileged))]
    return _rows(("index", "observation", "unit", "min", "max"), rows, indent)


def _spaces_text() -> str:
    """The docstring's action and observation spaces, their sizes as functions of the number of
    links n and at the default scenario's arm (from the table, so they cannot drift)."""
    n = _default_links()
    fixed, priv_fixed = len(observation_layout(0, False)), len(observation_layout(0, True))
    per, priv_per = len(observation_layout(1, False)) - fixed, len(observation_layout(1, True)) - priv_fixed
    base, full = len(observation_layout(n, False)), len(observation_layout(n, True))
    return f"""    ## Action Space
    ``Box(-1, 1, (n,), float32)``, one entry per joint: n is the scenario's number of links (3 for
    the paper's arm, the default). Non-finite actions or a wrong shape raise ``ValueError``; finite
    actions are clipped to [-1, 1].

    ## Observation Space
    ``Box(low, high, ({per} n + {fixed},), float32)``, ({base},) for the paper's {n}-link arm
    (``{priv_per} n + {priv_fixed}``, {full}, with ``privileged=True``). Unbounded quantities are
    squashed as c tanh(x / c) so every observation lies inside the box. The entries for the
    paper's arm (an arm of n links has n entries in each per-joint group):"""


def _privileged_entries() -> str:
    """The indices of the privileged entries at the default scenario's arm, "first-last"."""
    n = _default_links()
    return f"{len(observation_layout(n, False))}-{len(observation_layout(n, True)) - 1}"


def _default_text(v: Any) -> str:
    return "()" if v == () else repr(v)


def arguments_table(indent: str = "") -> str:
    """The env's keyword arguments (default, unit, accepted values, meaning), a Markdown table
    made from :data:`blf_gym.envs.envcore.ARGUMENTS` and :class:`~blf_gym.envs.envcore.EnvCore`'s defaults."""
    d = _defaults()
    rows = [(f"`{a.name}`", f"`{_default_text(d[a.name])}`", a.unit, a.accepted, a.meaning) for a in ARGUMENTS]
    return _rows(("argument", "default", "unit", "accepted", "meaning"), rows, indent)


def info_table(indent: str = "") -> str:
    """The env's ``info`` keys (unit, when present, meaning), a Markdown table made from
    :data:`blf_gym.envs.envcore.INFO_KEYS`."""
    rows = [(f"`{k.name}`", k.unit, k.when, k.meaning) for k in INFO_KEYS]
    return _rows(("key", "unit", "present", "meaning"), rows, indent)


def reward_terms_table(indent: str = "") -> str:
    """The shaped reward's per-sample terms (default weight, unit, meaning), a Markdown table made
    from :data:`blf_gym.kernel.reward.TERMS`."""
    from blf_gym.kernel.reward import TERMS

    rows = [(f"`{t.name}`", f"{t.weight:g}", t.unit, t.meaning.replace("``", "`")) for t in TERMS]
    return _rows(("term", "default weight", "unit", "per 1 ms sample, summed over the joints"), rows, indent)


def _defaults() -> dict[str, Any]:
    import inspect

    return {k: p.default for k, p in inspect.signature(EnvCore.__init__).parameters.items()
            if p.default is not inspect.Parameter.empty}


def _weights_text(w: Any) -> str:
    from dataclasses import fields

    return ", ".join(f"``{f.name}={getattr(w, f.name)!r}``" for f in fields(w))


def _reward_text() -> str:
    """The docstring's reward section, from the code's own defaults (so it cannot drift)."""
    from blf_gym.kernel.reward import PHI_CAP, SCORE_REWARD, RewardWeights

    d = _defaults()
    default = "the score reward" if d["reward_weights"] is None else repr(d["reward_weights"])
    first = textwrap.fill(
        f"The default (``reward_weights=None``) is {default}, :data:`blf_gym.kernel.reward.SCORE_REWARD`: "
        f"{_weights_text(SCORE_REWARD)}. Each step pays the change of a potential, the running log-ratio of "
        "the reference law's squared error to the policy's on the same scenario, so a full episode returns "
        "``log(score_vs_law)`` (0 for the law itself, > 0 for better tracking), whatever the control period; "
        f"the potential stays within +-{PHI_CAP:g}, and a violation costs {SCORE_REWARD.violation:g}, so "
        "every violating episode returns less than any other.", 96, initial_indent="    ", subsequent_indent="    ")
    second = textwrap.fill(
        "``reward_weights={}`` (or a :class:`blf_gym.kernel.reward.RewardWeights` / dict of its fields) gives the "
        f"shaped reward, with field defaults {_weights_text(RewardWeights())}::", 96,
        initial_indent="    ", subsequent_indent="    ")
    from blf_gym.kernel.reward import TERMS

    formula = " - ".join(["r = alive", *(f"{t.name} * E_{t.name}" for t in TERMS)])
    terms = "\n".join(textwrap.fill(f"E_{t.name}: the mean over the step's 1 ms samples and the joints of {t.meaning}.",
                                     96, initial_indent="    * ", subsequent_indent="      ") for t in TERMS)
    return f"""{first}

{second}

        {formula} + score * (phi_k - phi_(k-1)) - violation * [ended by it]
            - violation_rate * (violating share of the step's samples) [termination off]

    with

{terms}

    The env refuses weights under which ending an episode by a violation could pay (see
    :class:`~blf_gym.kernel.reward.RewardWeights`). The terms are returned in ``info["reward_info"]``,
    by name (``alive``, one per term, ``score`` and ``violation``)."""


def _truncation_text() -> str:
    """The docstring's truncation line, from the code's defaults."""
    from blf_gym.model.params import preset

    d = _defaults()
    dur = preset(d["scenario"]).sim.duration
    steps = int(round(dur / d["control_period"]))
    return f"""    * **Truncation**: at the scenario's duration in simulated time ({dur:g} s by default). The env
      truncates itself there; ``spec.max_episode_steps`` (and the ``max_episode_steps`` property) is
      that duration in agent steps, ``duration / control_period`` ({steps} with the defaults), set by
      ``gym.make`` without adding a ``TimeLimit``."""


class PlanarBLFEnv(gym.Env):
    __doc__ = f"""Track a Cartesian circle with the uncertain 3-DOF planar arm of Tran et al.
    (Electronics 2020, 9, 1355) while the joint errors stay inside time-varying bounds.

    ## Description
    The arm (point masses, friction, an asymmetric input dead-zone, an external force switched on
    at 20 s) is simulated with ODE3 at 0.1 ms by a compiled kernel; a linear extended state
    observer (LESO, k0 = 200) runs on the measured joint angles inside the env, so the agent
    gets velocity and disturbance estimates but never the true state (unless ``privileged``).
    Every agent step covers ``control_period`` (10 ms by default: 100 integration steps).
    ``n_links`` (2 to 7) makes the task family's arm of that many links instead of the paper's 3
    (docs/family.md); actions, observations and info arrays then have n entries per joint signal.

    * **Plain mode** (``PlanarBLF-v0``, ``controller=None``): the action is the torque,
      ``u = max_torque * a``.
    * **Residual mode** (``PlanarBLFResidual-v0`` or ``controller="proposed" | "lesobc" | "bc"``):
      the inner controller runs at every integration stage and the applied torque is
      ``u = u_law + residual_scale * a``, before the actuator limit and the dead-zone. The
      observer, observations, info and metrics all use that applied u.

{_spaces_text()}

{observation_table(True, '    ')}

    Entries {_privileged_entries()} exist only with ``privileged=True``. The measured angles include the optional
    noise (``angle_noise_std``, a fresh draw for the observation).

    ## Rewards
{_reward_text()}

    ## Starting State
    q(0) = q_d(0) + initial_error (zero in the paper presets), qd(0) = 0; observer
    x_hat(0) = [q(0), 0, 0]. A training env may start its episodes later along the reference
    (``start_time``): at t0, q = q_d(t0) + initial_error, qd = qd_d(t0), x_hat = [q, qd_d(t0), 0],
    the bounds those of t0. Scoring always starts at t = 0.

    ## Episode End
    * **Termination**: any joint error leaves (-k_b(t), k_a(t)) at any integration step
      (``info["termination_reason"] == "violation"``; off with ``terminate_on_violation=False``,
      which keeps running and counts violations in ``info["cost"]`` and
      ``info["violating_samples"]``); or the simulation diverges (``"diverged"``: non-finite or
      numerically unstable state, or a violation that ended the episode while the integration was
      unstable, reported with ``info["diverged_message"]`` and ``episode_metrics["diverged"]``;
      the observation is the last finite state, never NaN).
{_truncation_text()}

    ## Info
{info_table('    ')}

    The privileged observation's true x3 is that same sample's.

    ## Arguments
    ```python
    import gymnasium as gym
    import blf_gym
    env = gym.make("PlanarBLF-v0", scenario="paper-0.5hz", control_period=0.005)
    env = gym.make("PlanarBLFResidual-v0", controller="proposed", residual_scale=2.0)
    env = gym.make("PlanarBLF-v0", scenario="randomized")          # the randomized suite
    env = gym.make("PlanarBLFResidual-v0", n_links=5)              # the task family's 5-link arm
    obs, info = env.reset(seed=0, options={{"payload": 0.15}})       # per-episode variations
    ```
{arguments_table('    ')}

    ``render_mode`` ("rgb_array", "rgb_array_list", "human" or None) belongs to the single env.
    ``reset(options=...)`` takes the same variations per episode, applied last. ``control_period`` may also divide 1 ms (down to one integration
    step, as the sampled baseline policies use); steps without a 1 ms sample then have no
    tracking or torque term in their reward.

    Every argument, reset option and seed is checked before anything is built: a bad one raises
    ``ValueError`` naming it and what it accepts. Booleans must be booleans and numbers real
    numbers (a bool, a string, a complex number or NaN is refused; numpy scalars are accepted);
    ``dt`` must be at least 1e-7 s; ``reset(seed=...)`` takes None or an integer >= 0 (numpy
    integers included).

    ## Version History
    * v0: initial release.
    """

    metadata = {"render_modes": ["rgb_array", "rgb_array_list", "human"], "render_fps": 100}

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        """Keyword arguments are listed under *Arguments* above; their defaults live in
        :class:`blf_gym.envs.envcore.EnvCore`."""
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"PlanarBLFEnv: render_mode must be one of {self.metadata['render_modes']} or None, "
                             f"got {render_mode!r}")
        check_env_kwargs(kwargs)
        kwargs.setdefault("threads", 1)
        self.core = EnvCore(1, single=True, **kwargs)
        warn_if_oversubscribed(self.core.loop.threads, "PlanarBLFEnv")
        self.render_mode = render_mode
        n = self.core.n
        self.action_space = spaces.Box(-1.0, 1.0, (n,), dtype=np.float32)
        self.observation_space = spaces.Box(self.core.obs_low, self.core.obs_high, dtype=np.float32)
        self._renderer = None
        self._path: list[np.ndarray] = []
        self._needs_reset = True
        # a video's rate: one frame per control period, or one every k periods above MAX_FPS, so
        # that a recording's length equals simulated time (render_mode="rgb_array_list" renders
        # only those frames; "rgb_array" renders whenever it is asked)
        rate = 1.0 / self.core.control_period
        self.frame_every = max(1, int(np.ceil(rate / MAX_FPS - 1e-9)))
        self.metadata = {**self.metadata, "render_fps": rate / self.frame_every}
        self._frames: list[np.ndarray] = []
        self._spec = None

    @property
    def spec(self):
        """The env's :class:`gymnasium.envs.registration.EnvSpec`; its ``max_episode_steps`` is this
        env's own episode length in agent steps (``duration / control_period``), filled in when
        ``gym.make`` sets the spec, so wrappers that read it (``TimeAwareObservation``,
        sb3-contrib's ``TimeFeatureWrapper``) see the true length. The env truncates itself
        there; no ``TimeLimit`` is added."""
        return self._spec

    @spec.setter
    def spec(self, value) -> None:
        self._spec = self.core.with_episode_length(value)

    bound_scale = CORE_BOUND_SCALE

    @property
    def max_episode_steps(self) -> int:
        """Agent steps in a full episode: ``duration / control_period``."""
        return int(self.core.max_episode_steps)

    @property
    def scenario(self) -> Scenario:
        """The current episode's scenario."""
        return self.core.scenarios[0]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: ``(observation, info)``.

        ``seed`` (an integer >= 0) seeds the env's generator, which draws the episode's scenario
        (on a suite) and its measurement noise; the same seed gives the same episode to the bit.
        ``options`` varies this episode only: a mapping of the knobs of
        :data:`blf_gym.envs.scenarios.VARIATIONS` (e.g. ``{"force": 60.0}``), each checked
        against its safe range (ValueError naming it otherwise). ``info`` holds the step's keys
        (:data:`blf_gym.envs.envcore.INFO_KEYS`) and ``"scenario"``, the episode's
        ``Scenario`` (``blf_gym.model.params``)."""
        # checked before anything changes; a numpy integer seed is an integer
        seed = check_int("PlanarBLFEnv.reset:", "seed", seed, lo=0, none_ok=True)
        options = self.core.check_options(options)
        super().reset(seed=seed)
        self.core.rngs[0] = self.np_random
        self.core.reset_envs([0], options)
        batch: dict[str, Any] = {}
        obs = self.core.observe(batch)[0]
        info = self.core.info_row(batch, 0)
        info["scenario"] = self.scenario
        self._path = []
        self._needs_reset = False
        self._frames = []
        if self.render_mode == "human":
            self.render()
        elif self.render_mode == "rgb_array_list":
            self._frames.append(self._draw())
        return obs, info

    def step(self, action):
        """Hold ``action`` over one control period: ``(observation, reward, terminated, truncated,
        info)``.

        ``action``: n numbers in [-1, 1] (values outside are clipped): the torque over
        ``max_torque`` in plain mode, the residual over its scale in residual mode. NaN, inf or a
        wrong shape raise ValueError. ``terminated`` is a constraint violation (with
        ``terminate_on_violation``) or a diverged simulation (``info["termination_reason"]`` says
        which); ``truncated`` is the episode's end. After either, call :meth:`reset` (a further step
        raises RuntimeError)."""
        if self._needs_reset:
            raise RuntimeError("call reset() before step(), and again after an episode ends")
        obs, rew, term, trunc, batch = self.core.step(action)
        info = self.core.info_row(batch, 0)
        if term[0] or trunc[0]:
            self._needs_reset = True
        if self.render_mode == "human":
            self.render()
        elif self.render_mode == "rgb_array_list":
            k = int(self.core.steps[0])
            if k % self.frame_every == 0 or term[0] or trunc[0]:
                self._frames.append(self._draw())
        return obs[0], float(rew[0]), bool(term[0]), bool(trunc[0]), info

    def trajectory(self):
        """The current episode's signals on the 1 ms grid (a :class:`blf_gym.kernel.simulate.Trajectory`,
        the same type ``simulate()`` returns); needs ``record=True``."""
        return self.core.trajectory(0)

    def _draw(self) -> np.ndarray:
        from blf_gym.envs.render import ArmRenderer

        if self._renderer is None:
            self._renderer = ArmRenderer(self.scenario, human=self.render_mode == "human")
        return self._renderer.draw(self.core, 0, self._path)

    def render(self):
        """``rgb_array``: the current frame. ``rgb_array_list``: the frames since the last call,
        drawn at the video rate ``metadata["render_fps"]`` (every ``frame_every`` agent steps, and
        at the reset and the episode's last step), so Gymnasium's ``RecordVideo`` writes a video as
        long as the simulated time. ``human``: draws into a window."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self.render_mode == "rgb_array_list":
            frames, self._frames = self._frames, []
            return frames
        frame = self._draw()
        return frame if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def check_residual_controller(env_id: str, kwargs: dict[str, Any]) -> None:
    """ValueError if ``kwargs`` would make the residual id ``env_id`` run plain mode (``controller``
    None or ``"none"``: every action would become the whole torque, up to ``max_torque``)."""
    c = kwargs.get("controller", "proposed")
    if c is None or (isinstance(c, str) and c == "none"):
        raise ValueError(f"{env_id}: controller={c!r} would run plain mode (each action the whole torque, up to "
                         "max_torque) under the residual id; give a law (e.g. 'proposed', 'lesobc', 'bc' or a "
                         "registered plug-in), or make PlanarBLF-v0 for plain mode")


def make_env(**kwargs: Any) -> PlanarBLFEnv:
    """``PlanarBLF-v0``'s entry point: :class:`PlanarBLFEnv` with ``kwargs``.

    A function rather than the class, so that ``gym.make`` hands ``render_mode`` to the env's own
    check (a class entry point lets Gymnasium read it first, and a junk value such as ``True``
    failed inside ``gym.make`` with an AttributeError). The env renders every mode it lists
    natively, so nothing of Gymnasium's render wrapping is lost."""
    return PlanarBLFEnv(**kwargs)


def make_residual_env(**kwargs: Any) -> PlanarBLFEnv:
    """``PlanarBLFResidual-v0``'s entry point: as :func:`make_env`, and refuses a controller that
    would make it plain (:func:`check_residual_controller`)."""
    check_residual_controller("PlanarBLFResidual-v0", kwargs)
    return PlanarBLFEnv(**kwargs)

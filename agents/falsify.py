"""blf-falsify (also python -m agents.falsify): search the documented ranges for an episode where a
policy breaks a bound that the proposed law alone keeps.

A fixed list of held-out cases can be passed by a mechanism that fails one step beside them. The
verification field judges a controller's guarantee with a falsifier instead (S-TaLiRo, Breach, the
ARCH-COMP falsification category): an optimiser searches the admissible scenarios for a
counterexample to a temporal-logic property, guided by the property's robustness.

**The property** here is "where the law alone keeps every bound, the policy keeps every bound", on
one episode: ``G(-k_b < e1 < k_a)`` for the law implies the same for the policy, every joint, at
every 1 ms sample. Its robustness (the quantitative semantics of signal temporal logic) is

    rho = max(rho_policy, -rho_law),    rho_x = min over joints and samples of min(k_a - e1, e1 + k_b)

in degrees: the smallest margin to a bound, negative beyond it. rho < 0 exactly when the policy
leaves a bound in an episode where the law keeps them all (a counterexample); where the law itself
fails, rho >= 0 (the episode says nothing about the policy's certificate), and on the law itself
rho = |rho_law| >= 0, so the law has no counterexample by definition. rho_x is what
``blf_gym.results.metrics.episode_stats`` keeps per joint (``margin``); tests/test_falsify.py checks it
against rtamt's STL monitor on a recorded episode.

**The search**: each case is the paper's 0.1 Hz preset with every knob of
``blf_gym.envs.scenarios.SAFE_RANGES`` set (each joint's initial error apart) and a noise seed. The
edges of the box are tried first (its centre, each knob at either end with the others centred,
all low, all high, and seeded draws among its corners), then Optuna's sampler (TPE by default,
CMA-ES on request), seeded, proposes the rest, ``batch`` cases at a time, each batch one batched
run of the policy and one of the law through the compiled kernel. Repeated searches with
different seeds give the falsification rate (the share of searches that found a
counterexample) and the number of simulations to the first one, as the ARCH-COMP reports do.

    blf-falsify --agent agents/pretrained/ppo_residual_certified --budget 2000 --searches 3
    blf-falsify --controller ppc --budget 500
    blf-falsify --replay falsify/results.json --case 0:3     # one counterexample, re-simulated

No gain, threshold, seed or configuration of the project is chosen on a falsifier's counterexamples.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.results.io import atomic_write_json, help_text

BASE = "paper-0.1hz"
"""The preset every case varies (the training and stress suites draw around it too)."""
NOISE_SEEDS = (0, 2**31 - 1)
"""The range of a case's noise seed (its measurement noise, when its angle_noise_std is > 0)."""
FIRST_CORNERS = 16
"""Corners of the box drawn (seeded) among the first cases, beside its centre and edges."""


def space(ranges: dict[str, tuple[float, float]] | None = None, n: int | None = None) -> dict[str, tuple[float, float]]:
    """The searched box: each knob of ``ranges`` (default ``SAFE_RANGES``), a per-joint knob as one
    entry per joint (``initial_error_0`` ...) of an arm of ``n`` links (default: :data:`BASE`'s arm,
    the one every case varies), by name -> (low, high)."""
    from blf_gym.envs.scenarios import KNOBS, SAFE_RANGES, check_variations
    from blf_gym.model.params import preset

    n = preset(BASE).arm.n_links if n is None else n

    ranges = dict(SAFE_RANGES if ranges is None else ranges)
    per_joint = {k.name for k in KNOBS if k.per_joint}
    out: dict[str, tuple[float, float]] = {}
    for name, (lo, hi) in ranges.items():
        lo, hi = float(lo), float(hi)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"blf-falsify: the range of {name!r} must be finite numbers low <= high, got {(lo, hi)}")
        # each end must be a valid variation of the knob (names and physical limits checked)
        for v in (lo, hi):
            check_variations({name: (v,) * n if name in per_joint else v}, n, strict=False)
        if name in per_joint:
            out.update({f"{name}_{j}": (lo, hi) for j in range(n)})
        else:
            out[name] = (lo, hi)
    return out


def case_scenario(params: dict[str, float], box: dict[str, tuple[float, float]], duration: float | None = None):
    """(Scenario, noise seed) of one case: the base preset with the case's knobs."""
    from dataclasses import replace

    from blf_gym.model.params import preset
    from blf_gym.envs.scenarios import KNOBS, apply_variations

    per_joint = {k.name for k in KNOBS if k.per_joint}
    knobs: dict[str, Any] = {}
    joints: dict[str, list[tuple[int, float]]] = {}
    for name in box:
        head, _, j = name.rpartition("_")
        if head in per_joint and j.isdigit():
            joints.setdefault(head, []).append((int(j), float(params[name])))
        else:
            knobs[name] = float(params[name])
    for head, vals in joints.items():
        knobs[head] = tuple(v for _, v in sorted(vals))
    base = preset(BASE)
    if duration is not None:
        base = replace(base, sim=replace(base.sim, duration=float(duration)))
    return apply_variations(base, knobs, strict=False, name="falsify"), int(params.get("noise_seed", 0))


def first_cases(box: dict[str, tuple[float, float]], seed: int, corners: int = FIRST_CORNERS) -> list[dict[str, float]]:
    """The cases tried before the sampler's: the box's centre, each knob at its low and its high end
    with the others at the centre, all low, all high, and ``corners`` distinct corners drawn with
    ``default_rng(seed)``; noise seed 0 throughout."""
    names = list(box)
    mid = {k: (lo + hi) / 2 for k, (lo, hi) in box.items()}
    out = [dict(mid)]
    for k in names:
        for end in box[k]:
            out.append({**mid, k: end})
    out.append({k: box[k][0] for k in names})
    out.append({k: box[k][1] for k in names})
    rng = np.random.default_rng(seed)
    seen = set()
    for _ in range(corners * 20):
        if len(seen) >= min(corners, 2 ** len(names)):
            break
        bits = tuple(int(b) for b in rng.integers(0, 2, len(names)))
        if bits in seen or all(b == bits[0] for b in bits):
            continue
        seen.add(bits)
        out.append({k: box[k][b] for k, b in zip(names, bits)})
    return [{**c, "noise_seed": 0} for c in out]


# ---------------------------------------------------------------------------------------------
# the policy under test


@dataclass
class Target:
    """What is falsified: a trained agent (with its law reference on the env path), a registered
    policy, or a baseline controller (on the inner path); ``spec`` says how it was named."""

    name: str
    kind: str  # "agent", "policy" or "controller"
    spec: dict[str, Any]
    model: Any = None
    meta: dict[str, Any] | None = None
    norm: Any = None

    @classmethod
    def from_args(cls, agent: str | None = None, policy: str | None = None, controller: str | None = None,
                  residual_filter: str | None = None, accept_changed_files: bool = False) -> "Target":
        from .evaluate import with_filter
        from .loading import load_agent, load_policy

        given = [x for x in (agent, policy, controller) if x is not None]
        if len(given) != 1:
            raise ValueError("blf-falsify: name exactly one of --agent DIR, --policy NAME or --controller NAME")
        spec = {"agent": agent, "policy": policy, "controller": controller, "residual_filter": residual_filter}
        if controller is not None:
            from blf_gym.plugins.registry import available_controllers

            if controller not in available_controllers():
                raise ValueError(f"blf-falsify: --controller must be one of {available_controllers()}, got {controller!r}")
            if residual_filter is not None:
                raise ValueError("blf-falsify: --residual-filter acts on an agent's residual, not on a controller")
            return cls(controller, "controller", spec)
        # torch on one thread, as blf-eval: the network on a batch of 16 rows gains nothing from more,
        # and idle threads beside any other job made each call about 15 times slower (118 s for 16
        # simulations beside one training, 7.8 s on one thread); the actions are the same to the bit
        import torch

        torch.set_num_threads(1)
        if agent is not None:
            model, meta, norm = load_agent(agent, accept_changed_files=accept_changed_files)
            kind = "agent"
        else:
            model, meta, norm = load_policy(policy)
            kind = "policy"
        if residual_filter is not None:
            meta = with_filter(meta, residual_filter)
        return cls(meta.get("name", kind), kind, spec, model, meta, norm)

    def margins(self, scenarios: Sequence[Any], seeds: Sequence[int]) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        """(policy's rho, the law's rho, the policy's EpisodeStats) on each scenario, degrees."""
        from blf_gym.results.metrics import METRIC_CHANNELS, episode_stats

        from .evaluate import agent_group_episodes, law_reference_groups

        if self.kind == "controller":
            from blf_gym.kernel.simulate import LANES, simulate_batch

            pol = [episode_stats(t) for t in simulate_batch(scenarios, self.name, noise_seeds=seeds, lanes=LANES)]
            law = (pol if self.name == "proposed" else
                   [episode_stats(t) for t in simulate_batch(scenarios, "proposed", noise_seeds=seeds, lanes=LANES)])
        else:
            pol = [episode_stats(tr) for _, tr in agent_group_episodes(
                self.model, self.meta, self.norm, [list(scenarios)], channels=METRIC_CHANNELS,
                noise_seeds=[list(seeds)])]
            law = law_reference_groups([list(scenarios)], self.meta, noise_seeds=[list(seeds)])[0]
        return np.array([rho(s) for s in pol]), np.array([rho(s) for s in law]), pol


def rho(stats: Any) -> float:
    """An episode's robustness of ``G(-k_b < e1 < k_a)``, degrees: the smallest margin to a bound over
    joints and samples, negative beyond it; -inf for an episode that diverged before its first sample."""
    if stats.margin is None:
        return -np.inf
    r = float(np.degrees(np.min(stats.margin)))
    return -np.inf if stats.diverged and r >= 0 else r


def robustness(rho_policy: float, rho_law: float) -> float:
    """rho of "the law keeps every bound => the policy does": max(rho_policy, -rho_law)."""
    return max(rho_policy, -rho_law)


# ---------------------------------------------------------------------------------------------
# the search


@dataclass
class Search:
    """One search's record."""

    seed: int
    simulations: int = 0
    admissible: int = 0
    first_counterexample_at: int | None = None
    best: float = np.inf
    counterexamples: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "simulations": self.simulations, "admissible": self.admissible,
                "first_counterexample_at": self.first_counterexample_at, "lowest_robustness_deg": _finite(self.best),
                "counterexamples": self.counterexamples, "wall_s": round(self.wall_s, 1)}


def _finite(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def _sampler(name: str, seed: int):
    import optuna

    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, multivariate=True)
    if name == "cmaes":
        return optuna.samplers.CmaEsSampler(seed=seed, warn_independent_sampling=False)
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    raise ValueError(f"blf-falsify: --sampler must be tpe, cmaes or random, got {name!r}")


def search(target: Target, box: dict[str, tuple[float, float]], budget: int, seed: int, batch: int = 16,
           sampler: str = "tpe", duration: float | None = None, corners: int = FIRST_CORNERS,
           stop_at_first: bool = False, bar: Any = None) -> Search:
    """One seeded search of ``budget`` simulations (episodes of the policy; the law's run beside each
    is not counted). ``stop_at_first`` ends it at the batch holding its first counterexample."""
    try:
        import optuna
    except ImportError:
        raise ImportError("blf-falsify needs Optuna: pip install -e '.[sweep]'") from None
    from optuna.distributions import FloatDistribution, IntDistribution

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    dists: dict[str, Any] = {k: FloatDistribution(lo, hi) for k, (lo, hi) in box.items() if lo < hi}
    dists["noise_seed"] = IntDistribution(*NOISE_SEEDS)
    fixed = {k: lo for k, (lo, hi) in box.items() if lo == hi}
    study = optuna.create_study(direction="minimize", sampler=_sampler(sampler, seed))
    for c in first_cases(box, seed, corners)[:budget]:
        study.enqueue_trial({k: v for k, v in c.items() if k in dists})
    rec = Search(seed)
    t0 = time.perf_counter()
    while rec.simulations < budget:
        trials = [study.ask(dists) for _ in range(min(batch, budget - rec.simulations))]
        params = [{**fixed, **t.params} for t in trials]
        cases = [case_scenario(p, box, duration) for p in params]
        pol, law, stats = target.margins([c[0] for c in cases], [c[1] for c in cases])
        for t, p, rp, rl, st in zip(trials, params, pol, law, stats):
            r = robustness(rp, rl)
            # a divergence is +-inf: told as +-1e6, so that the law's own divergence (r = +inf) is
            # the least interesting case to the sampler and the policy's the most
            study.tell(t, float(np.clip(r, -1e6, 1e6)))
            rec.simulations += 1
            rec.admissible += int(rl > 0)
            rec.best = min(rec.best, r)
            if r < 0:
                if rec.first_counterexample_at is None:
                    rec.first_counterexample_at = rec.simulations
                rec.counterexamples.append({
                    "simulation": rec.simulations, "params": {k: (int(v) if k == "noise_seed" else float(v))
                                                               for k, v in p.items()},
                    "robustness_deg": _finite(r), "policy_margin_deg": _finite(rp), "law_margin_deg": _finite(rl),
                    "first_violation_s": st.first_violation_s, "diverged": bool(st.diverged)})
        if bar is not None:
            bar.update(len(trials))
        if stop_at_first and rec.counterexamples:
            break
    rec.wall_s = time.perf_counter() - t0
    return rec


def falsify(target: Target, box: dict[str, tuple[float, float]] | None = None, budget: int = 500,
            searches: int = 1, seed: int = 0, batch: int = 16, sampler: str = "tpe", duration: float | None = None,
            corners: int = FIRST_CORNERS, progress: bool = False) -> dict[str, Any]:
    """``searches`` seeded searches (seeds ``seed``, ``seed + 1``, ...) of ``budget`` simulations
    each; the report: the falsification rate, simulations to each search's first counterexample,
    every counterexample and the budget used."""
    box = space() if box is None else box
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=budget * searches, unit="episode", desc="blf-falsify", file=sys.stderr, leave=False)
    runs = [search(target, box, budget, seed + k, batch, sampler, duration, corners, bar=bar) for k in range(searches)]
    if bar is not None:
        bar.close()
    firsts = [r.first_counterexample_at for r in runs if r.first_counterexample_at is not None]
    return {
        "target": {"name": target.name, "kind": target.kind, **target.spec},
        "property": "the law keeps every bound => the policy keeps every bound (robustness max(rho_policy, -rho_law), deg)",
        "base": BASE, "duration": duration, "space": {k: list(v) for k, v in box.items()},
        "noise_seeds": list(NOISE_SEEDS), "sampler": sampler, "batch": batch, "first_corners": corners,
        "budget_per_search": budget, "searches": searches,
        "simulations": int(sum(r.simulations for r in runs)),
        "falsification_rate": len(firsts) / len(runs),
        "simulations_to_first": firsts,
        "counterexamples": int(sum(len(r.counterexamples) for r in runs)),
        "runs": [r.as_dict() for r in runs],
        "wall_s": round(sum(r.wall_s for r in runs), 1),
    }


def replay(report: dict[str, Any], run: int, case: int, accept_changed_files: bool = False) -> dict[str, Any]:
    """Re-simulate counterexample ``case`` of search ``run`` of a report: its margins now, beside the
    recorded ones (equal to the bit on the machine and code that found it).

    The case is simulated in a batch of the size of the one the search found it in, of copies of
    itself: an agent's network evaluated on 16 rows rounds differently from one row (a batched
    matrix product's blocking follows the batch's shape, not its other rows), so a lone replay of
    a case found in a batch of 16 differed from the record in the tenth digit."""
    t = report["target"]
    target = Target.from_args(t.get("agent"), t.get("policy"), t.get("controller"), t.get("residual_filter"),
                              accept_changed_files)
    try:
        ce = report["runs"][run]["counterexamples"][case]
    except (IndexError, KeyError):
        raise ValueError(f"blf-falsify --replay: no counterexample {run}:{case} in the report") from None
    box = {k: tuple(v) for k, v in report["space"].items()}
    sc, seed = case_scenario(ce["params"], box, report.get("duration"))
    width = int(report.get("batch", 1))
    first = (int(ce["simulation"]) - 1) // width * width  # simulations before the case's batch
    size = max(1, min(width, int(report.get("budget_per_search", width)) - first))
    pol, law, _ = target.margins([sc] * size, [seed] * size)
    now = {"robustness_deg": _finite(robustness(pol[0], law[0])), "policy_margin_deg": _finite(pol[0]),
           "law_margin_deg": _finite(law[0])}
    return {"params": ce["params"], "recorded": {k: ce[k] for k in now}, "now": now,
            "identical": all(now[k] == ce[k] for k in now)}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-falsify", description=help_text(__doc__.split("\n\n")[0]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    who = p.add_argument_group("the policy under test (one of)")
    who.add_argument("--agent", metavar="DIR", help="a blf-train run folder or shipped agent folder")
    who.add_argument("--policy", metavar="NAME", help="a registered policy (NAME or NAME:key=value,...)")
    who.add_argument("--controller", metavar="NAME", help="a registered controller, on the inner path")
    p.add_argument("--residual-filter", metavar="NAME", help="the agent through this filter of the proposed law "
                   "(barrier, cbf, barrier:handback=0.0033, barrier:handback=0.0033,lookahead=0.35) or 'none' "
                   "(default: the agent's own)")
    p.add_argument("--ranges", metavar="JSON", help="a JSON file of knob -> [low, high] to search instead of "
                   "SAFE_RANGES (default: blf_gym.envs.scenarios.SAFE_RANGES)")
    p.add_argument("--budget", type=int, default=500, help="simulations per search (default 500)")
    p.add_argument("--searches", type=int, default=1, help="independent searches, seeds SEED, SEED+1, ... (default 1)")
    p.add_argument("--seed", type=int, default=0, help="the first search's seed (default 0)")
    p.add_argument("--batch", type=int, default=16, help="cases simulated together (default 16)")
    p.add_argument("--sampler", default="tpe", choices=("tpe", "cmaes", "random"), help="Optuna sampler (default tpe)")
    p.add_argument("--duration", type=float, help="episode length in s (default the preset's 30)")
    p.add_argument("--out", metavar="DIR", help="write DIR/falsify.json (atomically, with provenance)")
    p.add_argument("--replay", metavar="JSON", help="re-simulate a counterexample of this report (with --case)")
    p.add_argument("--case", metavar="RUN:K", default="0:0", help="with --replay: search RUN's counterexample K "
                   "(default 0:0)")
    p.add_argument("--accept-changed-files", action="store_true", help="load an agent whose files differ from "
                   "its recorded hashes")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from blf_gym.results.metrics import provenance

    args = _parser().parse_args(argv)
    try:
        if args.replay:
            report = json.loads(Path(args.replay).read_text())
            run, _, k = args.case.partition(":")
            out = replay(report, int(run), int(k or 0), args.accept_changed_files)
            print(json.dumps(out, indent=2))
            return 0 if out["identical"] else 1
        for name in ("budget", "searches", "batch"):
            if getattr(args, name) < 1:
                raise ValueError(f"--{name} must be at least 1, got {getattr(args, name)}")
        ranges = json.loads(Path(args.ranges).read_text()) if args.ranges else None
        box = space(ranges)
        target = Target.from_args(args.agent, args.policy, args.controller, args.residual_filter,
                                  args.accept_changed_files)
        report = falsify(target, box, args.budget, args.searches, args.seed, args.batch, args.sampler,
                         args.duration, progress=not args.no_progress)
    except ValueError as exc:
        print(f"blf-falsify: {exc}", file=sys.stderr)
        return 2
    report["provenance"] = provenance(" ".join(["blf-falsify", *(argv if argv is not None else sys.argv[1:])]))
    if args.out:
        atomic_write_json(Path(args.out) / "falsify.json", report)
    print(f"blf-falsify: {target.name}: {report['counterexamples']} counterexample(s) in {report['simulations']} "
          f"simulations over {report['searches']} search(es); falsification rate {report['falsification_rate']:.2f}"
          + (f"; first at simulation {report['simulations_to_first']}" if report["simulations_to_first"] else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

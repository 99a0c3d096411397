"""Every generated table of the README and the documentation, rewritten by one command:

    python docs/tables.py            # rewrite them all
    python docs/tables.py --check    # exit 1, naming each file, if any differs (no writes)

A generated table sits between ``<!-- begin:NAME -->`` and ``<!-- end:NAME -->`` in its page and
is made either from the code's own declarations (the env's arguments, observation, reward terms
and info keys, the plug-in signals, the sweep file's keys, PPO-Lagrangian's hyperparameters) or
from a results file in ``docs/`` (never typed by hand). A results table whose runs left no file in
``docs/`` stays typed in its page, with a sentence under it saying so. The benchmark tables of
docs/speed.md and docs/conventions.md become generated once the benchmarks' ``--json`` files exist
in ``docs/speed/`` (:data:`MEASURED_BLOCKS`; the pages give the commands); until then they stay
typed. The control side's pages are written whole by ``docs/control/tables.py``, which this
command runs too.
``tests/test_docs_tables.py`` fails when anything here differs from what it would write.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent


def _module(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _env(name: str, *args: object) -> Callable[[], str]:
    """The table that ``blf_gym.envs.env.<name>(*args)`` makes (imported when asked for)."""
    def make() -> str:
        from blf_gym.envs import env

        return getattr(env, name)(*args)

    return make


HEADLINE = (
    # label, kind, results file under docs/, policy name there, the page with its full table
    ("proposed law (LESO + BLF, the paper's gains)", "control, certified", "protocol_control", "proposed",
     "control/protocol.md"),
    ("BC (the paper's)", "control", "protocol_control", "bc", "control/protocol.md"),
    ("LESOBC (the paper's)", "control", "protocol_control", "lesobc", "control/protocol.md"),
    ("proposed law, tuned gains (PPC's search)", "control, certified", "protocol_control", "proposed_tuned",
     "control/protocol.md"),
    ("prescribed-performance control", "control", "protocol_control", "ppc", "control/protocol.md"),
    ("PD + gravity compensation (true velocity)", "control", "protocol_control", "pd_gravity",
     "control/protocol.md"),
    ("PD + gravity compensation, on the LESO", "control", "protocol_control", "pd_gravity_leso",
     "control/protocol.md"),
    ("computed torque, on the LESO (over the torque budget)", "control", "protocol_control",
     "computed_torque_leso", "control/protocol.md"),
    ("funnel control", "control", "protocol_control", "funnel", "control/protocol.md"),
    ("nonlinear MPC", "control", "nmpc", "nmpc", "control/nmpc.md"),
    ("PPO residual over the law (seed 0 of 5)", "learning + law", "protocol_learners", "ppo_residual",
     "results.md"),
    ("PPO residual, barrier filter with hand-back (seed 0 of 5)", "learning + law", "protocol_learners",
     "ppo_residual_certified", "results.md"),
    ("PPO residual over the tuned law (seed 1 of 5, shipped)", "learning + law", "protocol_best",
     "res_proposed_tuned_s1", "results.md"),
    ("PPO residual over PPC (seed 1 of 5, shipped)", "learning + law", "protocol_best", "res_ppc_s1", "results.md"),
    ("plain PPO, searched (best plain learner)", "learning", "protocol_learners", "ppo_plain_searched",
     "plain_search.md"),
    ("plain PPO at 50M steps (sbx, seed 0 of 3)", "learning", "budget/protocol_s0", "sbx_ppo_256_s0", "budget.md"),
    ("SAC for PPO's wall clock (sbx, seed 0 of 3)", "learning", "budget/protocol_sac", "sbx_sac_s0", "budget.md"),
    ("PPO-Lagrangian, warm-started from plain PPO (seed 0 of 3)", "learning", "budget/protocol_warm",
     "ppo_lagrangian_warm_s0", "lagrangian.md"),
)
"""The headline comparison's rows: one per method, its shipped or best configuration."""

_GROUPS = ("paper-0.1hz", "paper-0.5hz", "randomized", "stress")
"""The protocol's four groups, in table order."""


def headline_table(prefix: str = "", here: str = "") -> str:
    """One row per method of :data:`HEADLINE`: ``score_vs_law`` on the presets, the training suite's
    held-out episodes and the stress suite (pooled RMSEs), the failures (presets failed of 2, and the
    suites' failure rates), the stress suite's ``certificate_broken`` and the wall time per 30 s
    episode over all four groups, as its own run measured it. Each method links to the
    page with its full table, ``prefix`` + the page (the README passes ``docs/``), unless that page
    is ``here``. A method whose results file is absent is left out."""
    cache: dict[str, list[dict]] = {}
    lines = ["| method (its full table) | kind | score 0.1 Hz / 0.5 Hz | score, training suite | score, stress | "
             "failures: presets / training / stress | certificate broken, stress | wall s per episode |",
             "|---|---|---|---|---|---|---|---|"]
    for label, kind, folder, policy, page in HEADLINE:
        path = DOCS / folder / "results.json"
        if not path.is_file():
            continue
        if folder not in cache:
            cache[folder] = _load(folder)["records"]
        rec = {r["scenario"]: r for r in cache[folder] if r["policy"] == policy}
        missing = [g for g in _GROUPS if g not in rec]
        if missing:
            raise ValueError(f"docs/{folder}/results.json: no {policy} record for {missing}")

        def sc(g: str) -> str:
            v = rec[g]["score_vs_law"]
            return "-" if v is None else f"{v:.3f}"

        presets = sum(rec[g]["failure_rate"] > 0 for g in ("paper-0.1hz", "paper-0.5hz"))
        name = label if page == here else f"[{label}]({prefix}{page})"
        lines.append(f"| {name} | {kind} | {sc('paper-0.1hz')} / {sc('paper-0.5hz')} | {sc('randomized')} | "
                     f"{sc('stress')} | {presets} of 2 / {rec['randomized']['failure_rate']:.2f} / "
                     f"{rec['stress']['failure_rate']:.2f} | {rec['stress']['certificate_broken']:.2f} | "
                     f"{sum(rec[g]['wall_s'] for g in _GROUPS) / sum(rec[g]['episodes'] for g in _GROUPS):.2f} |")
    return "\n".join(lines) + "\n"


CONTROL = _module(DOCS / "control" / "tables.py")
"""docs/control/tables.py, which writes the control side's pages."""
GROUP_LABEL: dict[str, str] = CONTROL.GROUPS
"""A scenario group's label in the tables (the control pages' own)."""


def _load(folder: str, name: str = "results.json") -> Any:
    import json

    return json.loads((DOCS / folder / name).read_text())


def _text(folder: str, name: str) -> str:
    """A results file that a command printed (not JSON), as text."""
    return (DOCS / folder / name).read_text()


def _rmse(v: float) -> str:
    """An RMSE in degrees: four decimals below 10, two below 1,000, whole degrees above."""
    return f"{v:.4f}" if v < 10 else (f"{v:.2f}" if v < 1000 else f"{v:,.0f}")


def _group(rec: dict) -> str:
    label = GROUP_LABEL.get(rec["scenario"], rec["scenario"])
    return label if rec["scenario"].startswith("paper") else f"{label} ({rec['episodes']})"


def _pick(records: list[dict], policy: str, scenario: str) -> dict:
    for r in records:
        if r["policy"] == policy and r["scenario"] == scenario:
            return r
    raise ValueError(f"no {policy} record for {scenario}")


def protocol_table() -> str:
    """The laws and the shipped agents of the default run, per group: BC, LESOBC and the proposed
    law, seed 0 of the residual and of the certified residual, and the first plain agent, from
    ``docs/protocol/results.json`` (the certified and the plain agent from ``docs/protocol_learners/``,
    the main job's latest run)."""
    main, learners = _load("protocol")["records"], _load("protocol_learners")["records"]
    rows = [("BC", main, "bc"), ("LESOBC", main, "lesobc"), ("proposed", main, "proposed"),
            ("**ppo_residual** (seed 0)", main, "ppo_residual_s0"),
            ("**ppo_residual_certified** (seed 0)", learners, "ppo_residual_certified"),
            ("ppo_plain", learners, "ppo_plain")]
    out = ["| policy | group | RMSE j1 (deg) | j2 | j3 | score_vs_law | violating samples | failure rate | "
           "certificate_broken |", "|---|---|---|---|---|---|---|---|---|"]
    for g in _GROUPS:
        for label, recs, policy in rows:
            r = _pick(recs, policy, g)
            out.append(f"| {label} | {_group(r)} | {' | '.join(_rmse(v) for v in r['rmse_deg'])} | "
                       f"{r['score_vs_law']:.3f} | {sum(r['violations']):,} | {r['failure_rate']:.2f} | "
                       f"{r['certificate_broken']:.2f} |")
    return "\n".join(out) + "\n"


def _ci(stat: dict, key: str, digits: int) -> str:
    lo, hi = stat[f"{key}_ci95" if key != "iqm" else "ci95"]
    v = stat[key]
    return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def statistics_table(folder: str, policies: tuple[str, ...], report: str = "report.json") -> str:
    """rliable's statistics per group (IQM of ``score_vs_law`` over seeds x episodes with its 95 %
    stratified-bootstrap interval, the probability of improvement over the law), from the
    ``statistics`` of ``python -m agents.report``'s JSON in ``docs/<folder>``; a group the run did
    not score is left out."""
    return statistics_rows_table([(policy, folder, report, policy) for policy in policies])


def statistics_rows_table(rows: Sequence[tuple[str, str, str, str]]) -> str:
    """:func:`statistics_table` for rows that may come from different runs: each row is (label,
    folder under docs/, its report, the policy name there), in the table's order within a group."""
    reports = {(folder, report): _load(folder, report)["statistics"] for _, folder, report, _ in rows}
    out = ["| policy | group | seeds x episodes | IQM score_vs_law [95 % CI] | P(improvement over the law) "
           "[95 % CI] | failure rate | certificate_broken |", "|---|---|---|---|---|---|---|"]
    for g in _GROUPS:
        for name, folder, report, policy in rows:
            stats = reports[(folder, report)]
            st = next((x for x in stats if x["policy"] == policy and x["scenario"] == g), None)
            if st is None and any(x["scenario"] == g for x in stats):
                raise ValueError(f"docs/{folder}/{report} has no statistics for {policy} on {g}")
            if st is None:  # a run without this group (e.g. no stress suite)
                continue
            label = GROUP_LABEL[g] if g.startswith("paper") else f"{GROUP_LABEL[g]} ({st['episodes']})"
            out.append(f"| {name} | {label} | {len(st['seeds'])} x {st['episodes']} | {_ci(st, 'iqm', 3)} | "
                       f"{_ci(st, 'prob_improvement', 2)} | {st['failure_rate']:.2f} | "
                       f"{st['certificate_broken']:.2f} |")
    return "\n".join(out) + "\n"


CERTIFIED_ROWS = (
    # label, folder under docs/, its report, the policy name there (a seed-pooled group)
    ("proposed", "protocol_certified", "report.json", "proposed"),
    ("ppo_residual", "protocol_certified", "report.json", "ppo_residual"),
    ("ppo_residual_certified, `barrier`", "protocol_certified_handback/barrier", "report.json",
     "ppo_residual_certified"),
    ("**ppo_residual_certified, `barrier:handback=0.0033`** (shipped)", "protocol_certified_handback/barrier_handback",
     "report.json", "ppo_residual_certified+barrier:handback=0.0033"),
)
"""The certified-statistics table's rows: the law and the unfiltered residual's five seeds, and the
certified residual's five seeds through the barrier filter without and with the hand-back."""


VERDICT_ROWS = (
    # label, the report (folder under docs/ and file), its pooled policy name, the runs' metadata files (globs)
    ("PPO residual over the law", "", "seeds_report.json", "ppo_residual", ("agents/pretrained/ppo_residual",)),
    ("PPO residual, barrier filter with hand-back", "protocol_certified_handback/barrier_handback", "report.json",
     "ppo_residual_certified+barrier:handback=0.0033",
     ("agents/pretrained/ppo_residual_certified", "docs/protocol_certified/runs/ppo_residual_certified_s*")),
    ("PPO residual over the tuned law", "protocol_best", "report.json", "res_proposed_tuned",
     ("docs/budget/runs/res_proposed_tuned_s*",)),
    ("PPO residual over the tuned law, barrier filter", "protocol_best", "report.json", "cert_proposed_tuned",
     ("docs/budget/runs/cert_proposed_tuned_s*",)),
    ("PPO residual over PPC", "protocol_best", "report.json", "res_ppc", ("docs/budget/runs/res_ppc_s*",)),
    ("plain PPO at scale (sbx)", "budget/protocol_scale", "report.json", "sbx_ppo_256",
     ("docs/budget/runs/sbx_ppo_256_s*",)),
    ("SAC for PPO's wall clock (sbx)", "budget/protocol_sac", "report.json", "sbx_sac", ("docs/budget/runs/sbx_sac_s*",)),
    ("PPO-Lagrangian, warm-started from plain PPO", "budget/protocol_warm", "report.json", "ppo_lagrangian_warm",
     ("docs/budget/runs/ppo_lagrangian_warm_s*",)),
    ("plain PPO, the same warm start", "budget/protocol_warm", "report.json", "ppo_warm",
     ("docs/budget/runs/ppo_warm_s*",)),
)
"""The learners of the verdict: rliable's statistics over their seeds, beside their budgets."""


def _budget(globs: tuple[str, ...]) -> tuple[int, str, str]:
    """(runs, agent steps per run, wall clock per run) from the runs' metadata: the range over runs
    when they differ. A run whose metadata is not in the repository (the residual's seeds 1-4) is
    not counted."""
    import json

    metas = [json.loads((f / "metadata.json").read_text()) for g in globs for f in sorted(ROOT.glob(g))
             if (f / "metadata.json").is_file()]
    steps = sorted({int(m["timesteps"]) for m in metas})
    walls = sorted(float(m["wall_s"]) for m in metas)

    def span(lo: float, hi: float, fmt) -> str:
        return fmt(lo) if fmt(lo) == fmt(hi) else f"{fmt(lo)} to {fmt(hi)}"

    return (len(metas), span(steps[0], steps[-1], lambda v: f"{v / 1e6:.1f}M"),
            span(walls[0], walls[-1], lambda v: f"{v / 3600:.1f} h" if v >= 3600 else f"{v / 60:.0f} min"))


RESIDUAL_RATE_PATHS = (("1. SB3, one thread", "residual_ppo_1t"), ("2. SB3, two threads", "residual_ppo_2t"),
                       ("3. sbx, one thread", "residual_sbx_1t"), ("4. sbx, all threads", "residual_sbx_2t"))
"""The shipped residual configuration's four measured paths (docs/budget.md, section 1): label, the
``benchmarks/bench_train.py --json`` file in docs/budget/rates/."""
ISSUE_RESIDUAL_RATE = 885
"""Agent steps/s of the shipped residual configuration as issue 25 states it (measured with a second
training on the two cores), the base of its five-fold goal."""


def residual_rates_table() -> str:
    """The residual configuration's agent steps/s on each path of :data:`RESIDUAL_RATE_PATHS`, end
    to end and without the learning-curve evaluations, against path 1 and the issue's figure."""
    runs = [(label, _load("budget/rates", f"{name}.json")) for label, name in RESIDUAL_RATE_PATHS]
    base = runs[0][1]["steps"] / runs[0][1]["wall_s"]
    out = ["| path | agent steps/s end to end | without curve evaluations | against path 1 | "
           f"against the first measured {ISSUE_RESIDUAL_RATE} |", "|---|---|---|---|---|"]
    for label, r in runs:
        rate = r["steps"] / r["wall_s"]
        out.append(f"| {label} | {rate:,.0f} | {r['steps'] / (r['wall_s'] - r['seconds']['curves']):,.0f} | "
                   f"{rate / base:.2f} | {rate / ISSUE_RESIDUAL_RATE:.1f} |")
    return "\n".join(out) + "\n"


FUSED_ROUNDS = 3
"""Interleaved rounds of path 2 and path 2 with PyTorch's fused Adam (docs/budget.md, section 1):
``docs/budget/rates/fused/r2_<k>.json`` and ``r5_<k>.json``, k = 1..FUSED_ROUNDS."""
FUSED_OVERRIDE = "policy_kwargs.optimizer_kwargs={fused: true, eps: 1.0e-5}"
"""The ``--set`` of the fused rounds: SB3's Adam eps (1e-5, which SB3 sets only when no
optimizer_kwargs are given) kept, so only the kernel differs."""


def fused_rounds_table() -> str:
    """Path 2 of :data:`RESIDUAL_RATE_PATHS` against the same path with a fused Adam step, measured in
    interleaved rounds: each round's agent steps/s and update seconds, the medians and their ratio."""
    import statistics

    rows = [(_load("budget/rates/fused", f"r2_{k}.json"), _load("budget/rates/fused", f"r5_{k}.json"))
            for k in range(1, FUSED_ROUNDS + 1)]
    for k, (a, b) in enumerate(rows, 1):
        if a["overrides"] != [] or b["overrides"] != [FUSED_OVERRIDE]:
            raise ValueError(f"docs/budget/rates/fused, round {k}: expected no --set, then --set {FUSED_OVERRIDE!r}; "
                             f"the files have {a['overrides']} and {b['overrides']}")
    rate = [[r["steps"] / r["wall_s"] for r in pair] for pair in rows]
    upd = [[r["seconds"]["update"] for r in pair] for pair in rows]
    out = ["| round | path 2: agent steps/s | its update (s) | path 2, fused Adam: agent steps/s | its update (s) |",
           "|---|---|---|---|---|"]
    for k, (a, b) in enumerate(rate):
        out.append(f"| {k + 1} | {a:,.0f} | {upd[k][0]:.1f} | {b:,.0f} | {upd[k][1]:.1f} |")
    med = [statistics.median(x[i] for x in rate) for i in (0, 1)]
    mu = [statistics.median(x[i] for x in upd) for i in (0, 1)]
    out.append(f"| median | {med[0]:,.0f} | {mu[0]:.1f} | {med[1]:,.0f} ({med[1] / med[0]:.2f}x; "
               f"{med[1] / ISSUE_RESIDUAL_RATE:.1f}x the first measured {ISSUE_RESIDUAL_RATE}) | "
               f"{mu[1]:.1f} ({mu[1] / mu[0]:.2f}x) |")
    return "\n".join(out) + "\n"


def verdict_table(prefix: str = "") -> str:
    """Each learner of :data:`VERDICT_ROWS`: seeds, agent steps and wall clock per run (from the runs'
    kept metadata), and rliable's IQM over seeds x episodes with its 95 % interval of its score
    against three yardsticks: the paper-gain law (``score_vs_law``, on the training suite's held-out
    episodes and on the stress suite: its 50 episodes, or the certificate's 100 where a report scored
    those; the cell says which), the reference controller (the second yardstick, on the training
    suite) and, for a residual over another law, that base law (on the training suite); and the
    failure rates."""
    from blf_gym.envs.protocol import REFERENCE

    out = ["| learner | seeds | agent steps per run | wall clock per run | IQM vs the law, training suite [95 % CI] | "
           "IQM vs the law, stress [95 % CI] (episodes per seed) | "
           f"IQM vs {REFERENCE.upper()}, training suite [95 % CI] | IQM vs its own base, training suite [95 % CI] | "
           "failure rate, training / stress |",
           "|---|---|---|---|---|---|---|---|---|"]
    stress_episodes = set()
    for label, folder, report, policy, globs in VERDICT_ROWS:
        stats = _load(folder, report)["statistics"]
        st = {x["scenario"]: x for x in stats if x["policy"] == policy}
        missing = [g for g in ("randomized", "stress") if g not in st]
        if missing:
            raise ValueError(f"docs/{folder}/{report} has no statistics for {policy} on {missing}")
        ref = st["randomized"].get("vs_reference")
        if ref is None or ref["against"] != REFERENCE:
            raise ValueError(f"docs/{folder}/{report} has no statistics for {policy} against {REFERENCE} "
                             f"(python -m agents.report RESULTS --reference {REFERENCE} --reference-results ...)")
        base = st["randomized"].get("vs_base")
        kept, steps, wall = _budget(globs)
        seeds = len(st["randomized"]["seeds"])
        if kept < seeds:
            wall += f" ({kept} of {seeds} runs' metadata kept)"
        stress_episodes.add(st["stress"]["episodes"])
        own = (f"{_ci(base, 'iqm', 3)} ({base['against']})" if base is not None else
               "= vs the law" if st["randomized"]["kind"] == "residual" else "-")
        out.append(f"| {label} | {seeds} | {steps} | {wall} | "
                   f"{_ci(st['randomized'], 'iqm', 3)} | {_ci(st['stress'], 'iqm', 3)} ({st['stress']['episodes']}) | "
                   f"{_ci(ref, 'iqm', 3)} | {own} | "
                   f"{st['randomized']['failure_rate']:.2f} / {st['stress']['failure_rate']:.2f} |")
    from blf_gym.envs.scenarios import STRESS_SEED_OFFSET as s0

    suite, *more = sorted(stress_episodes)
    out += ["", f"Stress episodes per seed: the suite's {suite} (seeds {s0}-{s0 + suite - 1})"
            + "".join(f", or {n} (seeds {s0}-{s0 + n - 1})" for n in more)
            + (f" where the certificate's report scored those ([the certificate]({prefix}certificate.md))." if more
               else ".")]
    return "\n".join(out) + "\n"


BEST_FOLDER = "protocol_best"
"""The residuals over the strongest bases (docs/budget/residual_best.sh, scored by
``docs/protocol_best/run.sh``)."""

BEST_ROWS = (
    # label, the seed-pooled policy in docs/protocol_best, its base law
    ("PPO residual over the tuned law", "res_proposed_tuned", "proposed_tuned"),
    ("PPO residual over the tuned law, barrier filter", "cert_proposed_tuned", "proposed_tuned"),
    ("PPO residual over PPC", "res_ppc", "ppc"),
)
"""Learning on top of the best controllers: the shipped residual's set-up (config, 1M agent steps,
seeds 0-4) over the tuned law (without and with the barrier filter, which applies to any gains of
the proposed law) and over PPC (no filter applies: PPC has no z2_hat)."""


def _torque(rec: dict) -> float:
    """A record's RMS torque over joints (N m): the root of the sum of the joints' squared RMS."""
    import math

    return math.sqrt(sum(v * v for v in rec["torque_rms"]))


def _best_parts() -> dict[str, Any]:
    """Per row of :data:`BEST_ROWS` and group: the residual's statistics, its base's (from the same
    report) and the ratio of their RMS torques (mean over seeds)."""
    from agents.report import seed_group

    stats = _load(BEST_FOLDER, "report.json")["statistics"]
    recs = _load(BEST_FOLDER)["records"]
    parts = {}
    for label, policy, base in BEST_ROWS:
        for g in _GROUPS:
            st = next((x for x in stats if x["policy"] == policy and x["scenario"] == g), None)
            bst = next((x for x in stats if x["policy"] == base and x["scenario"] == g), None)
            if st is None or bst is None:
                raise ValueError(f"docs/{BEST_FOLDER}/report.json lacks {policy} or {base} on {g}")
            mine = [r for r in recs if seed_group(r["policy"])[0] == policy and r["scenario"] == g]
            torque = sum(_torque(r) for r in mine) / len(mine) / _torque(_pick(recs, base, g))
            parts[(policy, g)] = {"stat": st, "base": bst, "torque_ratio": torque, "seeds": len(mine)}
    return parts


def best_table() -> str:
    """The residuals over the strongest bases beside their bases, per group: rliable's IQM over seeds x
    episodes with its 95 % interval of the score against the paper-gain law, against the reference
    controller and against the residual's own base, P(improvement over the base), failure rates
    (residual / base) and the RMS torque as a share of the base's."""
    parts = _best_parts()
    from blf_gym.envs.protocol import REFERENCE

    out = [f"| residual | group | seeds x episodes | IQM vs its base [95 % CI] | P(improvement over the base) [95 % CI] | "
           f"IQM vs the paper-gain law | IQM vs {REFERENCE.upper()} | failure rate, residual / base | RMS torque / base's |",
           "|---|---|---|---|---|---|---|---|---|"]
    for g in _GROUPS:
        for label, policy, base in BEST_ROWS:
            p = parts[(policy, g)]
            st, bst = p["stat"], p["base"]
            vs = st["vs_base"]
            ref = st.get("vs_reference")
            out.append(f"| {label} | {GROUP_LABEL[g]} | {p['seeds']} x {st['episodes']} | {_ci(vs, 'iqm', 3)} | "
                       f"{_ci(vs, 'prob_improvement', 2)} | {_ci(st, 'iqm', 3)} | "
                       f"{'-' if ref is None else _ci(ref, 'iqm', 3)} | "
                       f"{st['failure_rate']:.2f} / {bst['failure_rate']:.2f} | {p['torque_ratio']:.3f} |")
    return "\n".join(out) + "\n"


def best_verdict(indent: str = "") -> str:
    """The verdict on learning over the strongest controllers, in words, from :func:`best_table`'s
    numbers on the training suite and the stress suite (the README's, as a nested list with
    ``indent``, and results.md's)."""
    parts = _best_parts()
    stats = _load(BEST_FOLDER, "report.json")["statistics"]

    def answer(vs: dict) -> str:
        # the score is a geometric mean of RMSE ratios, so 1 / score is the RMSE as a share of the base's
        lo, hi = vs["ci95"]
        if lo > 1.0:
            return f"lowers its base's RMSE by {100 * (1 - 1 / vs['iqm']):.0f} %"
        if hi < 1.0:
            return f"raises its base's RMSE by {100 * (1 / vs['iqm'] - 1):.0f} %"
        return "does not measurably change its base's RMSE"

    lines = []
    for label, policy, base in BEST_ROWS:
        tr, sr = parts[(policy, "randomized")], parts[(policy, "stress")]
        vs = tr["stat"]["vs_base"]
        base_law = next(x for x in stats if x["policy"] == base and x["scenario"] == "randomized")
        lines.append(
            f"{indent}- **{label}** ({tr['seeds']} seeds) {answer(vs)} on the training suite: IQM {_ci(vs, 'iqm', 3)} "
            f"against its base, P(improvement) {vs['prob_improvement']:.2f}; against the paper-gain law "
            f"{tr['stat']['iqm']:.2f} (the base alone {base_law['iqm']:.2f}). On the stress suite: "
            f"{_ci(sr['stat']['vs_base'], 'iqm', 3)} against its base."
            + "".join(f" On the {GROUP_LABEL[g]} preset it {answer(parts[(policy, g)]['stat']['vs_base'])} "
                      f"({_ci(parts[(policy, g)]['stat']['vs_base'], 'iqm', 3)})."
                      for g in ("paper-0.1hz", "paper-0.5hz")
                      if parts[(policy, g)]["stat"]["vs_base"]["ci95"][0] <= 1.0)
            + " Failure rates, training / stress: "
            f"{tr['stat']['failure_rate']:.2f} / {sr['stat']['failure_rate']:.2f} (the base "
            f"{tr['base']['failure_rate']:.2f} / {sr['base']['failure_rate']:.2f}); RMS torque "
            f"{tr['torque_ratio']:.2f}x the base's on the training suite.")
    return "\n".join(lines) + "\n"


def levels_table() -> str:
    """The difficulty levels (blf_gym.envs.levels.LEVELS): what each keeps of a drawn scenario and what it
    changes."""
    from blf_gym.envs.levels import DEFAULT_LEVEL, LEVELS

    out = ["| level | name | plant | bounds | external force | episode names |", "|---|---|---|---|---|---|"]
    for lv in LEVELS:
        tag = "as the scenario's" if lv.number == DEFAULT_LEVEL else f"`<scenario>@L{lv.number}`"
        out.append(f"| {lv.number}{' (default)' if lv.number == DEFAULT_LEVEL else ''} | {lv.name} | {lv.plant} | "
                   f"{lv.bounds} | {lv.force} | {tag} |")
    return "\n".join(out) + "\n"


def audit_table() -> str:
    """The plain-learner audit (docs/plain_audit/summary.json, written by docs/plain_audit/report.py
    from the kept runs of docs/plain_audit/run.py): each variant's change against the candidate
    set-up and its learning curve's last point."""
    d = _load("plain_audit", "summary.json")
    out = ["| variant | what it changes | agent steps | wall (min) | score_vs_law, last point | failed episodes "
           "(of 6) | time before the first violation (s) | samples outside the bounds | RMSE 0.1 Hz (deg) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for v in d["variants"]:
        f = v["final"]
        rm = " / ".join(f"{x:.3g}" for x in f["rmse_deg"]["paper-0.1hz"])
        out.append(f"| `{v['name']}` | {v['what']} | {v['timesteps']:,} | {v['wall_s'] / 60:.0f} | "
                   f"{f['score_vs_law']:.3g} | {f['failed_episodes']} | {f['time_in_bounds_s']:.1f} | "
                   f"{f['violating_share']:.2f} | {rm} |")
    return "\n".join(out) + "\n"


LADDER_ROWS = (("the law (paper gains)", "proposed"), ("the law (tuned gains)", "proposed_tuned"), ("PPC", "ppc"),
               ("floor (10 ms)", "floor"), ("residual PPO over the tuned law (shipped, trained at L3)", "ppo_residual_tuned"),
               ("plain PPO, 2M steps per seed", "ppo_L{level}"), ("plain SAC, 2M steps per seed", "sac_L{level}"),
               ("plain PPO, 20M steps", "ppo_long_L{level}"),
               ("plain PPO, 2M steps, the full benchmark's reward", "ppo_bench_L{level}"))
"""The ladder's rows: label, the policy's pooled name in docs/ladder/L<level>/report.json ({level}
filled in); a row a level did not score is left out."""


def ladder_table() -> str:
    """The ladder (issue 61, item 6): per difficulty level, rliable's IQM of ``score_vs_law`` (against
    the paper-gain law on the same level's episodes) with its 95 % interval on the training suite's
    and the stress suite's held-out episodes, and the failure rates, from
    ``docs/ladder/L<level>/report.json`` (docs/ladder/eval.sh)."""
    from blf_gym.envs.levels import LEVELS, level_name

    out = ["| level | policy | seeds | IQM score, training suite [95 % CI] | IQM score, stress [95 % CI] | "
           "failure rate: presets / training / stress |", "|---|---|---|---|---|---|"]
    for lv in LEVELS:
        if not (DOCS / "ladder" / f"L{lv.number}" / "report.json").is_file():
            continue
        stats = _load(f"ladder/L{lv.number}", "report.json")["statistics"]
        tag = "" if lv.number == 3 else f"@L{lv.number}"
        for label, policy in LADDER_ROWS:
            name = policy.format(level=lv.number)
            st = {g: next((x for x in stats if x["policy"] == name and x["scenario"] == g + tag), None)
                  for g in _GROUPS}
            if st["randomized"] is None:
                continue
            pre = sum(st[g]["failure_rate"] > 0 for g in ("paper-0.1hz", "paper-0.5hz"))
            seeds = len([x for x in st["randomized"]["seeds"] if x is not None]) or "-"
            out.append(f"| {level_name(lv.number)} | {label} | {seeds} | {_ci_g(st['randomized'])} | "
                       f"{_ci_g(st['stress'])} | {pre} of 2 / {st['randomized']['failure_rate']:.2f} / "
                       f"{st['stress']['failure_rate']:.2f} |")
    return "\n".join(out) + "\n"


def _ci_g(stat: dict, key: str = "iqm") -> str:
    """:func:`_ci` in three significant digits (the ladder's scores span 1e-5 to 10)."""
    lo, hi = stat[f"{key}_ci95" if key != "iqm" else "ci95"]
    return f"{stat[key]:.3g} [{lo:.3g}, {hi:.3g}]"


def ladder_verdict(indent: str = "") -> str:
    """The README's verdict on learning without a law, from the ladder (docs/ladder/L<level>/
    report.json): per level, plain PPO's IQM score on the training suite with its interval and its
    failure rate, beside the floor's, in one sentence."""
    from blf_gym.envs.levels import LEVELS

    parts, seeds = [], set()
    for lv in LEVELS:
        if not (DOCS / "ladder" / f"L{lv.number}" / "report.json").is_file():
            continue
        stats = _load(f"ladder/L{lv.number}", "report.json")["statistics"]
        tag = "" if lv.number == 3 else f"@L{lv.number}"

        def st(policy: str) -> dict | None:
            return next((x for x in stats if x["policy"] == policy and x["scenario"] == "randomized" + tag), None)

        ppo, floor = st(f"ppo_L{lv.number}"), st("floor")
        if ppo is None or floor is None:
            continue
        seeds.add(len(ppo["seeds"]))
        parts.append(f"L{lv.number} {_ci_g(ppo)}, failing {ppo['failure_rate']:.0%} of the episodes "
                     f"(the floor {floor['iqm']:.3g}, {floor['failure_rate']:.0%})")
    if not parts:
        return ""
    n = "/".join(str(k) for k in sorted(seeds))
    return (f"{indent}On [the ladder](docs/levels.md#the-ladder), plain PPO with [the audited set-up](docs/plain_audit.md) "
            f"({n} seeds x 2M steps per level) scores, against the law on each level's training suite: "
            + "; ".join(parts) + ".\n")


FLOOR_ROWS = (("the law (paper gains)", "proposed"), ("floor, 10 ms", "floor"),
              ("floor, 1 ms (same gains)", "floor:control_period=0.001"))
"""The floor table's rows: label, the policy's name in docs/floor/L<level>/results.json."""


def floor_table() -> str:
    """The floor (baselines/floor.py) beside the law on every difficulty level, from
    ``docs/floor/L<level>/results.json`` (docs/floor/run.sh): scores against the paper-gain law on
    each level's presets, training suite and stress suite, the worst joint's RMSE on the 0.1 Hz
    preset, and the failure rates."""
    from blf_gym.envs.levels import LEVELS, level_name

    out = ["| level | policy | score 0.1 Hz / 0.5 Hz | score, training suite | score, stress | worst-joint RMSE, "
           "0.1 Hz (deg) | first violation, 0.1 Hz (s) | failures: presets / training / stress |",
           "|---|---|---|---|---|---|---|---|"]
    for lv in LEVELS:
        recs = _load(f"floor/L{lv.number}")["records"]
        tag = "" if lv.number == 3 else f"@L{lv.number}"
        for label, policy in FLOOR_ROWS:
            r = {g: _pick(recs, policy, g + tag) for g in _GROUPS}
            pre = sum(r[g]["failure_rate"] > 0 for g in ("paper-0.1hz", "paper-0.5hz"))
            first = r["paper-0.1hz"]["first_violation_s"]
            out.append(f"| {level_name(lv.number)} | {label} | {r['paper-0.1hz']['score_vs_law']:.3f} / "
                       f"{r['paper-0.5hz']['score_vs_law']:.3f} | {r['randomized']['score_vs_law']:.3f} | "
                       f"{r['stress']['score_vs_law']:.3f} | {max(r['paper-0.1hz']['rmse_deg']):.3f} | "
                       f"{'-' if first is None else f'{first:.2f}'} | {pre} of 2 / "
                       f"{r['randomized']['failure_rate']:.2f} / {r['stress']['failure_rate']:.2f} |")
    return "\n".join(out) + "\n"


def seeds_table() -> str:
    """Each residual seed's ``score_vs_law`` on the pooled RMSEs of each group, and whether it broke
    the certificate on the stress suite, from ``docs/protocol/results.json``."""
    recs = _load("protocol")["records"]
    seeds = sorted(int(r["policy"].rsplit("_s", 1)[1]) for r in recs
                   if r["policy"].startswith("ppo_residual_s") and r["scenario"] == "stress")
    out = ["| seed | 0.1 Hz | 0.5 Hz | training suite | stress | stress certificate_broken |",
           "|---|---|---|---|---|---|"]
    for k in seeds:
        r = {g: _pick(recs, f"ppo_residual_s{k}", g) for g in _GROUPS}
        out.append(f"| {k} | " + " | ".join(f"{r[g]['score_vs_law']:.3f}" for g in _GROUPS)
                   + f" | {r['stress']['certificate_broken']:.2f} |")
    return "\n".join(out) + "\n"


def learners_table() -> str:
    """The searched plain agent and PPO-Lagrangian beside the law, the residual and the first plain
    agent, from ``docs/protocol_learners/`` (results.json, and report.json for the IQM over
    episodes)."""
    recs = _load("protocol_learners")["records"]
    stats = _load("protocol_learners", "report.json")["statistics"]
    out = ["| policy | group | RMSE j1 (deg) | j2 | j3 | score_vs_law (pooled) | IQM score_vs_law over episodes | "
           "violating samples | failure rate | certificate_broken |", "|---|---|---|---|---|---|---|---|---|---|"]
    for policy, label in (("proposed", "proposed"), ("ppo_residual", "ppo_residual"), ("ppo_plain", "ppo_plain"),
                          ("ppo_plain_searched", "**ppo_plain_searched**"),
                          ("ppo_lagrangian", "**ppo_lagrangian**")):
        for g in _GROUPS:
            r = _pick(recs, policy, g)
            st = next(x for x in stats if x["policy"] == policy and x["scenario"] == g)
            out.append(f"| {label} | {_group(r)} | {' | '.join(_rmse(v) for v in r['rmse_deg'])} | "
                       f"{r['score_vs_law']:.3f} | {st['iqm']:.3f} | {sum(r['violations']):,} | "
                       f"{r['failure_rate']:.2f} | {r['certificate_broken']:.2f} |")
    return "\n".join(out) + "\n"


def reproduction_table() -> str:
    """The paper's six cases beside its Tables 3-4, from ``docs/reproduction/results.json``
    (``blf-reproduce --out docs/reproduction``) and ``baselines.reproduce.PAPER_RMSE_DEG``."""
    from baselines.reproduce import PAPER_RMSE_DEG

    recs = _load("reproduction")["records"]
    names = {"bc": "BC", "lesobc": "LESOBC", "proposed": "proposed"}
    out = ["| case | controller | RMSE j1 | j2 | j3 | paper j1 | j2 | j3 | violating 1 ms samples (j1/j2/j3) | "
           "peak torque (N m) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for g in ("paper-0.1hz", "paper-0.5hz"):
        for c in ("bc", "lesobc", "proposed"):
            r = _pick(recs, c, g)
            viol = "/".join(str(int(v)) for v in r["violations"])
            if sum(r["violations"]) == 0 and c == "proposed":
                viol = f"**{viol}**"
            out.append(f"| {GROUP_LABEL[g]} | {names[c]} | {' | '.join(f'{v:.4f}' for v in r['rmse_deg'])} | "
                       f"{' | '.join(f'{v:.4f}' for v in PAPER_RMSE_DEG[(g, c)])} | {viol} | "
                       f"{'/'.join(f'{v:.1f}' for v in r['torque_peak'])} |")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------
# docs/tuning.md: the residual agent's search

_CURVE_GROUPS = ("paper-0.1hz", "paper-0.5hz", "randomized")
"""The learning curve's groups (both presets and the held-out training-suite episodes), in table order."""


def certificate_cases_table() -> str:
    """The shipped certified agent on the 120 held-out certificate cases through each filter,
    without and with the hand-back, beside the law alone, from ``docs/certificate_cases/*/results.json``
    (``docs/certificate_cases/run.sh``)."""
    out = ["| policy | filter | episodes | score_vs_law | violating samples | failure rate | "
           "episodes breaking the certificate |", "|---|---|---|---|---|---|---|"]
    law = None
    rows = []
    for path in sorted((DOCS / "certificate_cases").glob("*/results.json")):
        for r in _load(f"certificate_cases/{path.parent.name}")["records"]:
            if r["kind"] == "baseline":
                law = r
                continue
            spec = r["env_kwargs"].get("residual_filter") or "none"
            broken = round(r["certificate_broken"] * r["episodes"])
            rows.append((spec, f"| {r['policy'].split('+')[0]} | `{spec}` | {r['episodes']} | {r['score_vs_law']:.3f} | "
                               f"{sum(r['violations']):,} | {r['failure_rate']:.2f} | {broken} |"))
    if law is None:
        return "No results yet: `docs/certificate_cases/run.sh` writes them.\n"
    out.append(f"| proposed law alone | - | {law['episodes']} | 1.000 | {sum(law['violations']):,} | "
               f"{law['failure_rate']:.2f} | - |")
    order = {"barrier": 0, "cbf": 2}
    rows.sort(key=lambda x: (order.get(x[0].split(":")[0], 9), x[0]))
    return "\n".join(out + [row for _, row in rows]) + "\n"


def certified_seeds_table() -> str:
    """The certified residual's five training seeds through the barrier filter, without and with the
    hand-back: rliable's IQM on the training suite, the stress suite and the presets, from
    ``docs/protocol_certified_handback/{barrier,barrier_handback}/report.json``, and each seed on the
    120 held-out certificate cases with the hand-back, from ``.../certificate_handback/results.json``
    (``docs/protocol_certified_handback/run.sh``)."""
    out = ["| filter | group | seeds x episodes | IQM score_vs_law [95 % CI] | failure rate | certificate_broken |",
           "|---|---|---|---|---|---|"]
    for folder, spec in (("barrier", "barrier"), ("barrier_handback", "barrier:handback=0.0033")):
        stats = _load(f"protocol_certified_handback/{folder}", "report.json")["statistics"]
        for g in ("randomized", "stress", "paper-0.1hz", "paper-0.5hz"):
            st = next(x for x in stats if x["policy"].startswith("ppo_residual_certified") and x["scenario"] == g)
            label = GROUP_LABEL[g] if g.startswith("paper") else f"{GROUP_LABEL[g]} ({st['episodes']})"
            out.append(f"| `{spec}` | {label} | {len(st['seeds'])} x {st['episodes']} | {_ci(st, 'iqm', 3)} | "
                       f"{st['failure_rate']:.2f} | {st['certificate_broken']:.2f} |")
    text = "\n".join(out) + "\n"
    path = DOCS / "protocol_certified_handback" / "certificate_handback" / "results.json"
    if path.is_file():
        recs = _load("protocol_certified_handback/certificate_handback")["records"]
        law = next(r for r in recs if r["kind"] == "baseline")
        rows = ["| seed | episodes | score_vs_law | violating samples | failure rate | episodes breaking the certificate |",
                "|---|---|---|---|---|---|",
                f"| the law alone | {law['episodes']} | 1.000 | {sum(law['violations']):,} | {law['failure_rate']:.2f} | - |"]
        agents = sorted((r for r in recs if r["kind"] != "baseline"),
                        key=lambda r: int(re.search(r"_s(\d+)", r["policy"]).group(1)))
        for r in agents:
            seed = re.search(r"_s(\d+)", r["policy"]).group(1)
            rows.append(f"| {seed} | {r['episodes']} | {r['score_vs_law']:.3f} | {sum(r['violations']):,} | "
                        f"{r['failure_rate']:.2f} | {round(r['certificate_broken'] * r['episodes'])} |")
        text += "\nOn the held-out certificate cases, with the hand-back:\n\n" + "\n".join(rows) + "\n"
    return text


def _triple(values: list[float], digits: int = 3) -> str:
    return " ".join(f"{v:.{digits}f}" for v in values)


def oracle_table() -> str:
    """The disturbance oracle's RMSE over the law's, per control period and group, from
    ``docs/tuning/oracle.txt`` (``python -m agents.oracle > docs/tuning/oracle.txt``; its defaults are
    the periods 10, 5 and 2 ms and 4 held-out suite episodes)."""
    ratios: dict[float, dict[str, str]] = {}
    group = None
    for line in _text("tuning", "oracle.txt").splitlines():
        head = re.match(r"(\S+): law alone", line)
        row = re.match(r"\s*oracle, control period\s+([\d.]+) ms: .* ratio ([\d. ]+)$", line)
        if head:
            group = head.group(1)
        elif row:
            ratios.setdefault(float(row.group(1)), {})[group] = row.group(2).strip()
    out = ["| control period | 0.1 Hz j1 j2 j3 | 0.5 Hz j1 j2 j3 | suite j1 j2 j3 |", "|---|---|---|---|"]
    for period, by_group in ratios.items():
        out.append(f"| {period:g} ms | " + " | ".join(by_group[g] for g in _CURVE_GROUPS) + " |")
    return "\n".join(out) + "\n"


ROUND_NOTES = {
    "ppo_t100_scale05": "residual_scale 0.5", "ppo_t100": "residual_scale 2",
    "ppo_t100_normrew": "VecNormalize rewards", "ppo_t100_cp2ms": "control period 2 ms",
    "ppo_t100_scale8": "residual_scale 8", "ppo_t100_cp5ms": "control period 5 ms",
    "sac_t100_scale05": "{k}k steps, stopped", "sac_t100": "{k}k", "sac_t100_normrew": "{k}k",
    "ppo_rel_scale8": "residual_scale 8", "ppo_rel_scale8_g95": "gamma 0.95", "ppo_rel": "residual_scale 2",
    "ppo_rel_std3": "residual_scale 2, log_std_init -3", "ppo_rel_scale8_cp5ms": "5 ms",
    "ppo_rel_scale8_sde": "gSDE exploration",
}
"""What a search run changed, shown after its name (``{k}``: its steps in thousands); the configs
are in ``docs/tuning/configs/``."""


def _round_table(*files: str) -> str:
    """The runs of ``docs/tuning/<file>.json`` (one search round, as the first ``blf-tune`` wrote
    ``OUT/tune.json``), each file's runs ranked by the geometric mean of their nine RMSE ratios to the
    law. When the best run of the table beats the law on that mean, its name, each group where it
    beats the law on all three joints, and the mean are in bold."""
    runs = [r for f in files for r in sorted(_load("tuning", f"{f}.json")["rows"], key=lambda r: r["mean_ratio"])]
    best = min(runs, key=lambda r: r["mean_ratio"])
    bold = best["mean_ratio"] < 1
    out = ["| run | RMSE / law, 0.1 Hz (j1 j2 j3) | 0.5 Hz | suite | geo-mean | worst |", "|---|---|---|---|---|---|"]
    for r in runs:
        mark = bold and r is best
        note = ROUND_NOTES.get(r["run"], "").format(k=r["timesteps"] // 1000)
        name = f"**{r['run']}**" if mark else r["run"]
        cells = [f"{name} ({note})" if note else name]
        for g in _CURVE_GROUPS:
            text = _triple(r[g]["ratio"])
            cells.append(f"**{text}**" if mark and max(r[g]["ratio"]) < 1 else text)
        cells.append(f"**{r['mean_ratio']:.3f}**" if mark else f"{r['mean_ratio']:.3f}")
        cells.append(f"{r['worst_ratio']:.3f}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def tuning_round1_table() -> str:
    """Round 1 (the env's absolute reward): PPO then SAC, from ``docs/tuning/round1_ppo.json`` and
    ``round1_sac.json`` (``blf-tune`` over that round's configs in ``docs/tuning/configs/``,
    ``--timesteps 300000`` for PPO, 100000 for SAC)."""
    return _round_table("round1_ppo", "round1_sac")


def tuning_round2_table() -> str:
    """Round 2 (the reward measured against the law), from ``docs/tuning/round2_ppo_relative.json``
    (``blf-tune`` over the ``ppo_rel*`` configs in ``docs/tuning/configs/``, ``--timesteps 300000``)."""
    return _round_table("round2_ppo_relative")


FINAL_SEEDS_300K = ("ppo_residual_s0", "ppo_residual_s1", "ppo_residual_s2")
"""The first release's three final seeds: run folders under ``docs/tuning/final_300k/``."""

OBS_VARIANTS = (
    ("ppo_final_privileged", "`privileged: true` (true velocity and disturbance added; not deployable)"),
    ("ppo_final_no_obs_norm", "`normalize: false` (no observation normalization)"),
)
"""The observation variants of the final config: run folder under ``docs/tuning/obs/``, row label."""


def _ratios_at(folder: str, steps: int, law: dict) -> list[list[float]]:
    """A run's RMSE over the law's per group of :data:`_CURVE_GROUPS`, at its curve point of
    ``steps`` (``docs/<folder>/eval/curve.json``)."""
    p = next(q for q in _load(f"{folder}/eval", "curve.json")["points"] if q["timesteps"] == steps)
    return [[a / b for a, b in zip(p[g]["rmse_deg"], law[g])] for g in _CURVE_GROUPS]


def observation_variants_table(steps: int = 300_000) -> str:
    """The final config's three seeds, then each observation variant, as RMSE over the law's at
    their curve point of ``steps``. The seeds' curves are ``docs/tuning/final_300k/<run>/eval/curve.json``
    (the first release's final runs, ``blf-train`` with the final config, 1M steps; restored from
    commit c6754a8's ``docs/curves/``); the variants' are ``docs/tuning/obs/<run>/eval/curve.json``
    (``blf-train --config docs/tuning/configs/<run>.yaml --timesteps 1000000``, stopped after 300k
    steps). The law's RMSE on the same curve scenarios is the ``law`` of ``docs/tuning/round1_ppo.json``.
    The seeds' ratios have two decimals (three runs share a cell, as first printed), the variants' three."""
    law = _load("tuning", "round1_ppo.json")["law"]
    out = ["| variant | RMSE / law, 0.1 Hz (j1 j2 j3) | 0.5 Hz | suite |", "|---|---|---|---|"]
    seeds = [_ratios_at(f"tuning/final_300k/{run}", steps, law) for run in FINAL_SEEDS_300K]
    out.append(f"| final config, seeds 0 / 1 / 2 at {steps // 1000}k | "
               + " | ".join(" / ".join(_triple(s[i], 2) for s in seeds) for i in range(len(_CURVE_GROUPS))) + " |")
    for run, label in OBS_VARIANTS:
        out.append(f"| {label} | " + " | ".join(_triple(r) for r in _ratios_at(f"tuning/obs/{run}", steps, law)) + " |")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------
# docs/budget.md, docs/sweeps.md, docs/plain_search.md, docs/lagrangian.md, docs/extending.md


LAGRANGIAN_RUNS = (("lagrangian_s0_presets", "ppo_lagrangian_s0", "none"),
                  ("lagrangian_cur_s0_presets", "ppo_lagrangian_cur_s0", "`{bound_scale: 15, until: 1000000}`"),
                  ("ppo_cur_s0_presets", "ppo_cur_s0", "`{bound_scale: 15, until: 1000000}`"),
                  ("lagrangian_tc_s0_presets", "ppo_lagrangian_tc_s0", "none; termination_cost 3000"),
                  ("lagrangian_sched_s0_presets", "ppo_lagrangian_sched_s0",
                   "none; termination_cost 3000; limit 3000 to 25 over 2M steps"),
                  ("lagrangian_shaped_s0_presets", "ppo_lagrangian_shaped_s0",
                   "none; termination_cost 3000; limit 3000 to 25 over 2M steps; plain PPO's reward"),
                  ("lagrangian_warm_s0_presets", "ppo_lagrangian_warm_s0",
                   "none; warm start from ppo_plain; termination_cost 3000; limit 2800 to 25 over 2M steps; "
                   "plain PPO's reward, not normalised"),
                  ("ppo_warm_s0_presets", "ppo_warm_s0", "none; plain PPO, warm start from ppo_plain"),
                  ("protocol_warm", "ppo_lagrangian_warm_s1", "as ppo_lagrangian_warm_s0, seed 1"),
                  ("protocol_warm", "ppo_lagrangian_warm_s2", "as ppo_lagrangian_warm_s0, seed 2"),
                  ("protocol_warm", "ppo_warm_s1", "as ppo_warm_s0, seed 1"),
                  ("protocol_warm", "ppo_warm_s2", "as ppo_warm_s0, seed 2"))
"""The seed-0 runs of budget.md section 4 (PPO-Lagrangian after its fix, without and with the funnel
curriculum, plain PPO with the same curriculum, PPO-Lagrangian charged for terminated episodes, with
a cost-limit schedule as well, with plain PPO's reward, and warm-started from plain PPO, beside plain
PPO given the same warm start), then seeds 1 and 2 of the last two, scored on the whole protocol
(``docs/budget/scale_eval.sh``, whose preset episodes are those of ``--suite-seeds 0``): folder under
docs/budget, agent, curriculum (and the other set-up changes)."""


def lagrangian_presets_table() -> str:
    """The runs of :data:`LAGRANGIAN_RUNS` on both presets, from ``docs/budget/<folder>/results.json``
    (``blf-eval --agents docs/budget/runs/<agent> --suite-seeds 0 --out DIR``), against the item's
    targets: no divergence, no turnover, at most 10 % violating samples; a run not yet scored is
    left out."""
    out = ["| run | set-up (curriculum; other changes) | preset | RMSE per joint (deg) | violating samples (worst joint's share) | "
           "largest excursion beyond a bound (deg) | diverged | score_vs_law |", "|---|---|---|---|---|---|---|---|"]
    for folder, agent, curriculum in LAGRANGIAN_RUNS:
        if not (DOCS / "budget" / folder / "results.json").is_file():
            continue
        recs = _load(f"budget/{folder}")["records"]
        for g in ("paper-0.1hz", "paper-0.5hz"):
            r = _pick(recs, agent, g)
            diverged = f"yes, first violation at {r['first_violation_s']:.3f} s" if r["diverged"] else "no"
            out.append(f"| {agent} | {curriculum} | {GROUP_LABEL[g]} | {' / '.join(f'{v:.1f}' for v in r['rmse_deg'])} | "
                       f"{sum(r['violations']):,} ({max(r['violation_fraction']):.0%}) | {max(r['max_excursion_deg']):.1f} | "
                       f"{diverged} | {r['score_vs_law']:.3f} |")
    return "\n".join(out) + "\n"


SCALING_RUNS = (
    ("c1", "local Ray", None),
    ("c2", "local Ray", "speedup_c2_over_c1"),
    ("cluster", "two-node cluster (`ray.cluster_utils.Cluster`, 1 CPU per node, both on 127.0.0.1)",
     "speedup_cluster_over_c1"),
)
"""The scaling benchmark's three sweeps: key in its JSON, row label, key of the speed-up over ``c1``."""


def sweep_scaling_table() -> str:
    """One sweep of 8 short trials run three ways, from ``docs/sweeps/scaling.json``
    (``python benchmarks/sweep_scaling.py --json docs/sweeps/scaling.json``)."""
    res = _load("sweeps", "scaling.json")
    out = ["| run | nodes | trials at once | wall time (8 trials) | speed-up |", "|---|---|---|---|---|"]
    for key, label, speedup in SCALING_RUNS:
        r = res[key]
        out.append(f"| {label} | {r['nodes']} | {r['concurrency']} | {r['wall_s']:.1f} s | "
                   f"{f'{res[speedup]:.2f}x' if speedup else '1'} |")
    return "\n".join(out) + "\n"


SWEEP_KEY_DOCS: dict[tuple[str, ...], tuple[str, str]] = {
    ("name",): ("the sweep's name; runs are named `<name>-<config id>_s<seed>`", "the file's stem"),
    ("base",): ("the `blf-train` config (a path, resolved next to the sweep file, then in `agents/configs/`)",
                "`<algo>_<env id>.yaml`"),
    ("algo", "mode", "controller", "observer", "scenario"):
        ("`blf-train`'s options, any registered algorithm, controller or observer by name; `scenario: stress` "
         "is refused", "ppo, residual, proposed, leso, randomized"),
    ("timesteps",): ("the budget of every trial, in agent steps", "300000"),
    ("seeds",): ("every configuration is trained once per seed", "`[0]`"),
    ("search",): ("`grid`, `random` (Optuna's `RandomSampler`) or `optuna` (Optuna's `TPESampler`)", "grid"),
    ("num_samples",): ("configurations to sample (random, optuna)", "required for them"),
    ("search_seed",): ("the seed of the sampler, so the same file proposes the same configurations", "0"),
    ("overrides",): ("fixed changes to the base config, by dotted key", "none"),
    ("space",): ("the search space, by dotted key", "none"),
    ("scheduler",): ("`{asha: {grace_period, reduction_factor, brackets}}`, in agent steps", "none"),
    ("concurrency",): ("trials at the same time", "one per CPU of the cluster"),
    ("time_budget_s",): ("wall-clock seconds for the whole sweep: Ray Tune stops every trial when they run out "
                         "(status `budget`, ranked on its last curve point) and starts no more; a resume counts "
                         "the seconds already spent (`OUT/budget.json`), so stopping and resuming never renews "
                         "the budget", "none"),
    ("note",): ("free text for the reader; a resume does not compare it", "none"),
}
"""What each key of a sweep file means and its default (keys that share a row are listed together)."""


def sweep_keys_table() -> str:
    """The keys a sweep file accepts, in the order of ``agents.sweep.SPEC_KEYS`` (the declaration
    ``blf-sweep`` checks a file against), described by :data:`SWEEP_KEY_DOCS`."""
    from agents.sweep import SPEC_KEYS

    described = [k for keys in SWEEP_KEY_DOCS for k in keys]
    if sorted(described) != sorted(SPEC_KEYS):
        raise ValueError(f"SWEEP_KEY_DOCS describes {sorted(described)}; agents.sweep.SPEC_KEYS is {sorted(SPEC_KEYS)}")
    out = ["| key | meaning | default |", "|---|---|---|"]
    for keys in sorted(SWEEP_KEY_DOCS, key=lambda ks: SPEC_KEYS.index(ks[0])):
        meaning, default = SWEEP_KEY_DOCS[keys]
        out.append(f"| {', '.join(f'`{k}`' for k in keys)} | {meaning} | {default} |")
    return "\n".join(out) + "\n"


PLAIN_SWEEPS = ("ppo_lagrangian", "plain_ppo", "plain_sac", "plain_tqc")
"""The sweeps of the plain and constrained learners, ``docs/sweeps/<name>.json``, in table order."""


def plain_search_table() -> str:
    """Budget, trials and best configuration of each sweep of :data:`PLAIN_SWEEPS`, from
    ``docs/sweeps/<name>.json`` (``OUT/sweep.json`` of ``blf-sweep agents/configs/sweeps/<name>.yaml
    --out OUT``; the PPO-Lagrangian grid's file is ``lagrangian.yaml``). Agent steps are each trial's
    steps at its last curve point, summed."""
    out = ["| algorithm | budget (s) | spent (s) | trials started | done / budget-stopped / pruned / error | "
           "agent steps, all trials | best objective | best score_vs_law (0.1 Hz / 0.5 Hz / suite) | "
           "failed curve episodes of the best | best configuration |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name in PLAIN_SWEEPS:
        d = _load("sweeps", f"{name}.json")
        n, best = d["counts"], d["configs"][0]
        budget = d.get("time_budget_s")
        spent = d.get("budget_used_s", d["wall_s"])
        best_scores = {g: v["score"] for g, v in best["groups"].items()}
        out.append(f"| {d['spec']['algo']} | {budget or '-'} | {spent:.0f} | {len(d['trials'])} | "
                   f"{' / '.join(str(n.get(k, 0)) for k in ('done', 'budget', 'pruned', 'error'))} | "
                   f"{sum(t['timesteps'] for t in d['trials']):,} | {best['objective']:.4f} | "
                   f"{' / '.join(f'{best_scores[g]:.3f}' for g in _CURVE_GROUPS)} | "
                   f"{best['failed_episodes']} | {', '.join(f'{k}={v}' for k, v in sorted(best['params'].items()))} |")
    return "\n".join(out) + "\n"


LAGRANGIAN_HYPERPARAMETERS = {
    "cost_limit": ("allowed cost per episode, in cost units (PlanarBLF: violating control steps)", "finite, >= 0"),
    "lagrangian_lr": ("lambda's step per unit of excess episode cost",
                      "finite, >= 0 (0: a fixed penalty `lagrangian_init`)"),
    "lagrangian_init": ("lambda at the start", "finite, >= 0"),
    "termination_cost": ("cost added on a step that ends its episode by termination (not the time limit), so "
                         "ending an episode early cannot lower its cost", "finite, >= 0 (0: none)"),
    "cost_limit_start": ("the limit at step 0, moving linearly to `cost_limit` over `cost_limit_steps` agent "
                         "steps", "finite, >= 0, or None (no schedule)"),
    "cost_limit_steps": ("agent steps over which the limit moves from `cost_limit_start` to `cost_limit`",
                         "integer >= 0; > 0 when `cost_limit_start` is set"),
}
"""What each of PPO-Lagrangian's own hyperparameters means and accepts."""


def family_members_table() -> str:
    """The task family's arms (blf_gym.model.family.family_table): links, masses, reach, the largest
    gravity and force torques at the base, the lightest mode, and the proposed law's carried gains."""
    import numpy as np

    from baselines.params import fastest_pole
    from blf_gym.model.dynamics import mass_matrix
    from blf_gym.model.family import family_arm, family_presets, family_table
    from blf_gym.envs.envcore import named_block

    out = ["| n | links (m) | masses (kg) | reach (m) | gravity at the base (N m) | 40 N force at the base (N m) | "
           "lightest mode (kg m^2) | presets |", "|---|---|---|---|---|---|---|---|"]
    for row in family_table():
        n = row["n"]
        arm = family_arm(n)
        qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (512, n))
        lightest = min(np.linalg.eigvalsh(mass_matrix(q, arm)).min() for q in [np.zeros(n), *qs])
        ls = ", ".join(f"{x:g}" for x in row["lengths"]) if len(set(row["lengths"])) > 1 else f"{n} x {row['lengths'][0]:g}"
        ms = ", ".join(f"{x:g}" for x in row["masses"]) if len(set(row["masses"])) > 1 else f"{n} x {row['masses'][0]:g}"
        out.append(f"| {n} | {ls} | {ms} | {row['reach']:.2f} | {row['gravity_torque']:.2f} | "
                   f"{row['force_torque']:.1f} | {lightest:.2e} | {', '.join(f'`{p}`' for p in family_presets(n))} |")
    out += ["", "| n | K1 (1/s) | K2 (N m s/rad) | fastest velocity pole (1/s) |", "|---|---|---|---|"]
    for n in (2, 3, 4, 5, 6, 7):
        arm = family_arm(n)
        g = named_block("tables:", "controller", "proposed", arm).params
        out.append(f"| {n} | {', '.join(f'{x:.4g}' for x in g.K1)} | {', '.join(f'{x:.4g}' for x in g.K2)} | "
                   f"{fastest_pole(g.K2, arm):.4g} |")
    return "\n".join(out) + "\n"


def family_law_table() -> str:
    """The proposed law on each member (docs/family/law.json, python docs/family/run.py): per member
    and group (its presets, its training-suite draws), the worst joint's RMSE, the largest torque,
    and how many episodes broke a bound or diverged."""
    data = _load("family", "law.json")
    out = ["| n | episodes | RMSE, worst joint (deg) | largest torque (N m) | broke a bound | diverged |",
           "|---|---|---|---|---|---|"]
    for n in sorted({r["n"] for r in data["records"]}):
        for group, pick in (("presets", lambda r: not r["scenario"].startswith("randomized")),
                            (f"training suite, seeds 0-{data['draws'] - 1}", lambda r: r["scenario"].startswith("randomized"))):
            rs = [r for r in data["records"] if r["n"] == n and pick(r)]
            out.append(f"| {n} | {len(rs)} ({group}) | {max(max(r['rmse_deg']) for r in rs):.3f} | "
                       f"{max(max(r['max_torque']) for r in rs):.1f} | {sum(r['violating_samples'] > 0 for r in rs)} | "
                       f"{sum(r['diverged'] for r in rs)} |")
    return "\n".join(out) + "\n"


def family_protocol_table() -> str:
    """The protocol on every member of the task family (docs/family/protocol/results.json, written by
    ``blf-eval --n-links 2 3 4 5 6 7 --controllers proposed ppc funnel --out docs/family/protocol``):
    per member and controller, ``score_vs_law`` on the pooled RMSEs of the presets, the training suite's
    held-out episodes and the stress suite, with the share of episodes that broke a bound or diverged
    (the law's own in its row)."""
    recs = _load("family/protocol")["records"]

    def group(scenario: str) -> str:
        for g in ("randomized", "stress"):
            if scenario.endswith(g):
                return g
        return "presets"

    def n_of(scenario: str) -> int:
        return int(scenario[1]) if scenario.startswith("n") and scenario[1].isdigit() else 3

    out = ["| n | controller | presets: score (fail) | training suite: score (fail) | stress suite: score (fail) |",
           "|---|---|---|---|---|"]
    policies = list(dict.fromkeys(r["policy"] for r in recs))
    for n in sorted({n_of(r["scenario"]) for r in recs}):
        for pol in policies:
            cells = []
            for g in ("presets", "randomized", "stress"):
                rs = [r for r in recs if r["policy"] == pol and n_of(r["scenario"]) == n and group(r["scenario"]) == g]
                if not rs:
                    cells.append("-")
                    continue
                eps = sum(r["episodes"] for r in rs)
                fail = sum(r["failure_rate"] * r["episodes"] for r in rs) / eps
                score = " / ".join(f"{r['score_vs_law']:.3f}" for r in rs)
                cells.append(f"{score} ({fail:.2f} of {eps})")
            out.append(f"| {n} | {pol} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def family_headline_table() -> str:
    """The headline's block per member of the task family (docs/family/score.json, written by
    ``python docs/family/score.py`` from the protocol and learner runs on the members): rliable's IQM
    of the per-episode score against the law with its 95 % interval, on the training suite's held-out
    episodes and on the stress suite, and the share of episodes failed, for PPC, the best residual
    learner and the best plain learner (each the best of its kind by its training-suite IQM, never by
    the stress suite), with the law's own failure shares; the controllers PPC and the tuned law, each
    with its gains searched on the member ("-" where a member has no run of it)."""
    rows = _load("family", "score.json")["rows"]

    def cell(r: dict | None) -> str:
        if r is None:
            return "not trained yet"
        seeds = len(r["seeds"]) if r["seeds"] and r["seeds"][0] is not None else 0
        who = "" if r["kind"] == "baseline" else f"{r['policy']}, {seeds} seed{'s' if seeds != 1 else ''}: "
        return f"{who}{r['iqm']:.3g} [{r['ci95'][0]:.3g}, {r['ci95'][1]:.3g}] ({r['failure_rate']:.2f})"

    out = ["| n | group | the law: failed | PPC | the tuned law | best residual learner | best plain learner |",
           "|---|---|---|---|---|---|---|"]
    for n in sorted({r["n"] for r in rows}):
        best = {}
        for kind in ("residual", "plain"):
            train = [r for r in rows if r["n"] == n and r["kind"] == kind and r["group"] == "randomized"]
            best[kind] = max(train, key=lambda r: r["iqm"])["policy"] if train else None
        for group, label in (("randomized", "training suite"), ("stress", "stress suite")):
            at = {r["policy"]: r for r in rows if r["n"] == n and r["group"] == group}
            law = at.get("proposed")
            law_failed = "-" if law is None else f"{law['failure_rate']:.2f}"
            control = [cell(at[c]) if c in at else "-" for c in ("ppc", "proposed_tuned")]
            out.append(f"| {n} | {label} | {law_failed} | {' | '.join(control)} | "
                       f"{cell(at.get(best['residual']))} | {cell(at.get(best['plain']))} |")
    return "\n".join(out) + "\n"


def family_ppc_gains_table(law: str = "ppc") -> str:
    """A law's gain search on each member of the task family (docs/gains/family/<law>_n<N>/gains.json,
    ``python -m baselines.gains LAW --n-links N``; PPC's, or the proposed law's for the tuned law,
    whose paper-arm gains are PPC's): the carried gains' point and the chosen one, with their scores
    and efforts on the member's selection episodes."""
    import json

    out = ["| n | carried K1, K2 (first joint) | carried: score (effort), failed on | chosen K1, K2 | chosen: score (effort) |",
           "|---|---|---|---|---|"]
    for path in sorted((DOCS / "gains" / "family").glob(f"{law}_n*/gains.json"),
                       key=lambda p: int(p.parent.name.rsplit("_n", 1)[1])):
        d = json.loads(path.read_text())
        n = d["n_links"]
        rows = d["rows"]
        rule = next((r for r in rows if r["point"]["K1"] == 1280.0
                     and abs(r["point"]["K2"] - _carried_ppc_k2(n)) < 1e-9 * _carried_ppc_k2(n)), None)
        chosen = rows[0] if d["chosen"] else None
        rtxt = "not on the grid" if rule is None else (f"{rule['score_geomean']:.3f} ({rule['effort_ratio']:.2f}), "
                                                       f"{', '.join(rule['failed_on']) or 'none'}")
        out.append(f"| {n} | 1280, {_carried_ppc_k2(n):.4g} | {rtxt} | "
                   + (f"{chosen['point']['K1']:g}, {chosen['point']['K2']:.4g} | {chosen['score_geomean']:.3f} "
                      f"({chosen['effort_ratio']:.2f}) |" if chosen else "none | - |"))
    return "\n".join(out) + "\n"


def _carried_ppc_k2(n: int) -> float:
    """The first entry of PPC's K2 (and the tuned law's, the same vector) carried to the member of
    ``n`` links by the rule alone."""
    from baselines.params import velocity_gain
    from blf_gym.model.family import family_arm

    return velocity_gain((11.25, 11.25, 3.75), family_arm(n))[0]


def family_cost_table() -> str:
    """The closed loop's cost per arm-step per member and the fit (docs/speed/links.json, written by
    ``python benchmarks/bench_links.py --json docs/speed/links.json``)."""
    d = _load("speed", "links.json")
    a, b, c = d["fit_a_b_c"]
    out = ["| n | " + " | ".join(str(n) for n in d["n"]) + " |", "|---|" + "---|" * len(d["n"]),
           "| us per arm-step | " + " | ".join(f"{u:.3f}" for u in d["us_per_arm_step"]) + " |",
           "| fit a + b n + c n^2 | " + " | ".join(f"{a + b * n + c * n * n:.3f}" for n in d["n"]) + " |"]
    return "\n".join(out) + (f"\n\nFit: a = {a:.3f}, b = {b:.3f}, c = {c:.4f} us; log-log slope from n = {d['n'][0]} "
                             f"to {d['n'][-1]}: {d['loglog_slope']:.2f} (minimum of {d['repeats']} calls of "
                             f"{d['steps']} steps per member).\n")


def lagrangian_hyperparameters_table() -> str:
    """PPO-Lagrangian's own hyperparameters with their defaults, in the order of
    ``PPOLagrangian.__init__`` in ``agents/lagrangian.py`` (read from its source, so that torch is
    not imported), described by :data:`LAGRANGIAN_HYPERPARAMETERS`."""
    import ast

    source = (ROOT / "agents" / "lagrangian.py").read_text()
    cls = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef) and n.name == "PPOLagrangian")
    init = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
    named = init.args.args[len(init.args.args) - len(init.args.defaults):]
    defaults = {a.arg: ast.get_source_segment(source, d) for a, d in zip(named, init.args.defaults)
                if not a.arg.startswith("_")}
    if sorted(defaults) != sorted(LAGRANGIAN_HYPERPARAMETERS):
        raise ValueError(f"PPOLagrangian takes {sorted(defaults)}; LAGRANGIAN_HYPERPARAMETERS describes "
                         f"{sorted(LAGRANGIAN_HYPERPARAMETERS)}")
    out = ["| name | meaning | accepted | default |", "|---|---|---|---|"]
    for name, default in defaults.items():
        meaning, accepted = LAGRANGIAN_HYPERPARAMETERS[name]
        out.append(f"| `{name}` | {meaning} | {accepted} | {default.removesuffix('.0')} |")
    return "\n".join(out) + "\n"


SIGNAL_ROWS = (
    (("t",), "time"),
    (("y",), "measured joint angles (true angles plus measurement noise)"),
    (("qd_true", "q_true"),
     "true joint velocities and angles: a full-state law (results say so), or a filter's monitor"),
    (("u_max",), "the actuator's torque limit"),
    (("q_d", "qd_d", "qdd_d"), "the joint reference and its derivatives"),
    (("k_a", "k_a_dot", "k_a_ddot"), "the upper error bound and its rates"),
    (("k_b", "k_b_dot", "k_b_ddot"), "the lower bound: the error stays in (-k_b, k_a)"),
    (("nominal",), "the nominal model at `y`, for the operators below"),
    (("work",), "scratch, undefined on entry"),
)
"""The signals every plug-in may read (``blf_gym.plugins.blocks.BASE_SIGNALS``), grouped into rows, with
what each row is; sizes and units come from the declaration."""

BLOCK_SIGNAL_ROWS = (
    "| observer states | declared | declared | e.g. the LESO's `x1_hat`, `x2_hat`, `x3_hat` |",
    "| controller outputs | declared | declared | `u_law` and any extras (after `Controller.output`) |",
    "| `u` | n | N m | the commanded torque: law + residual, after the limit, before the dead-zone "
    "(after `Controller.output`) |",
    "| own parameters | field | field | each numeric field of the block's parameter dataclass, by name |",
    "| own states, `state` | declared | declared | the block's states by name, or all of them |",
)
"""The signals that depend on the blocks of the loop, after the base ones."""


def signals_table() -> str:
    """The signals a plug-in function may read: the base signals from
    ``blf_gym.plugins.blocks.BASE_SIGNALS`` (size and unit), grouped by :data:`SIGNAL_ROWS`, then
    :data:`BLOCK_SIGNAL_ROWS`."""
    from blf_gym.plugins.blocks import BASE_SIGNALS, work_length

    listed = [k for names, _ in SIGNAL_ROWS for k in names]
    if sorted(listed) != sorted(BASE_SIGNALS):
        raise ValueError(f"SIGNAL_ROWS lists {sorted(listed)}; BASE_SIGNALS declares {sorted(BASE_SIGNALS)}")
    if any(work_length.py_func(n) != 2 * n * n + 12 * n for n in (1, 2, 3, 7)):
        raise ValueError("blf_gym.plugins.blocks.work_length is no longer 2n^2 + 12n: update signals_table")
    size_text = {"model": "-", "work": "2n^2 + 12n"}
    out = ["| signal | size | unit | what |", "|---|---|---|---|"]
    for names, what in SIGNAL_ROWS:
        sizes = {BASE_SIGNALS[k][0] for k in names}
        if len(sizes) != 1:
            raise ValueError(f"the signals {names} of one row have different sizes {sorted(sizes)}")
        size = sizes.pop()
        out.append(f"| {', '.join(f'`{k}`' for k in names)} | {size_text.get(size, size)} | "
                   f"{', '.join(BASE_SIGNALS[k][1] for k in names)} | {what} |")
    out.extend(BLOCK_SIGNAL_ROWS)
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------
# docs/speed.md, docs/conventions.md: benchmark measurements, from the benchmarks' --json files
# in docs/speed/ (benchmarks/results_json.py). A table is generated only once its files exist.


def _span(values: list[float], fmt: Callable[[float], str]) -> str:
    """``values`` as ``lo-hi`` (one figure when both print the same), each formatted by ``fmt``."""
    lo, hi = fmt(min(values)), fmt(max(values))
    return lo if lo == hi else f"{lo}-{hi}"


def _dec(digits: int) -> Callable[[float], str]:
    return lambda v: f"{v:,.{digits}f}"


def _hundreds(v: float) -> str:
    return f"{round(v, -2):,.0f}"


def _measured(doc: dict) -> str:
    """Where and when a benchmark file was measured, for the line under its table."""
    load = doc["load_avg"][0] if doc.get("load_avg") else "unknown"
    return (f"on {doc['date'][:10]} at commit {doc['commit']}, {doc['cpus']} CPUs, "
            f"1-minute load average {load} at the start")


def _resets_cell(runs: list[dict]) -> str:
    """``bench_resets.py``'s runs: the loop's rate and a reset's median, p99 and worst, in ms and in
    residual steps; the worst again from the runs with the garbage collector off, if any."""
    on, off = [r for r in runs if r["gc"]], [r for r in runs if not r["gc"]]
    if not on:
        raise ValueError("docs/speed/resets.json has no run with Python's garbage collector on")

    def reset(runs: list[dict], stat: str) -> str:
        ms = _span([r["reset_ms"][stat] for r in runs], _dec(2))
        steps = _span([r["reset_ms"][stat] / (r["residual_step_us"] / 1e3) for r in runs], _dec(1))
        return f"{ms} ms ({steps} steps)"

    text = (f"{_span([r['steps_per_s'] for r in on], lambda v: f'{round(v, -1):,.0f}')} steps/s, episodes of "
            f"{_span([r['steps'] / r['resets'] for r in on], _dec(1))} steps; a reset's median {reset(on, 'median')}, "
            f"p99 {reset(on, 'p99')}, the worst of a run ({_span([r['resets'] for r in on], _dec(0))} resets) "
            f"{reset(on, 'max')}")
    if off:
        text += (f"; with Python's garbage collector off (`--no-gc`), the worst {reset(off, 'max')}, "
                 f"{_span([r['reset_cpu_ms']['max'] for r in off], _dec(2))} ms of the thread's own CPU time")
    return text


def speed_table() -> str:
    """The headline speeds beside their targets, as the range of each figure's median over separate
    runs, from ``docs/speed/core.json``, ``env.json`` and ``resets.json`` (each run of
    ``python benchmarks/bench_core.py --json docs/speed/core.json``, ``bench_env.py --json
    docs/speed/env.json`` and ``bench_resets.py [--no-gc] --json docs/speed/resets.json`` adds one)."""
    core, env = _load("speed", "core.json")["runs"], _load("speed", "env.json")["runs"]
    resets = _load("speed", "resets.json")["runs"]

    def step(ctrl: str) -> str:
        return _span([r["step_us"][ctrl] for r in core], _dec(2))

    def env_us(env_id: str) -> str:
        return _span([r["env_step_us"][env_id] for r in env], _dec(0))

    def rate(n: int, threads: int) -> str:
        return _span([next(v["steps_per_s"] for v in r["vector"] if (v["num_envs"], v["threads"]) == (n, threads))
                      for r in env], _hundreds)

    rows = [
        ("one closed-loop step (plant + LESO + proposed law, 3 ODE3 stages), amortized over a 30 s run",
         f"{step('proposed')} us (BC {step('bc')}, LESOBC {step('lesobc')}, no law {step('none')})", "<= 0.8 us"),
        ("`blf-reproduce`, six cases, process start included, warm cache",
         f"{_span([r['reproduce_s'] for r in core], _dec(1))} s", "<= 3 s"),
        ("residual `env.step` through `gym.make` (100 integration steps)",
         f"{env_us('PlanarBLFResidual-v0')} us (plain {env_us('PlanarBLF-v0')} us; Pendulum-v1: "
         f"{env_us('Pendulum-v1')} us)", "<= 100 us"),
        ("vector env, residual, N = 64", f"{rate(64, 2)} agent steps/s on 2 threads ({rate(64, 1)} on 1)", ">= 15,000"),
        ("plain `PlanarBLF-v0`, training suite, random actions, default reward (`benchmarks/bench_resets.py`; "
         "episodes end at a violation, so mostly resets)", _resets_cell(resets),
         ">= 1,000 steps/s, no reset over 20 steps"),
    ]
    out = ["| what | measured | target |", "|---|---|---|"] + [f"| {a} | {b} | {c} |" for a, b, c in rows]
    runs = "; ".join(f"`{script}` {len(r)} run{'s' if len(r) > 1 else ''}, the last {_measured(r[-1])}"
                     for script, r in (("bench_core.py", core), ("bench_env.py", env), ("bench_resets.py", resets)))
    return "\n".join(out) + f"\n\nRanges of the medians over separate runs: {runs}.\n"


COMPARE_ROWS = (
    ("step_us", "closed-loop step (proposed + LESO), one arm, no noise", " us", 3),
    ("batch64_us", "one step per arm, 64 mixed training-suite arms with noise, 1 thread", " us", 3),
    ("env_us", "residual `env.step`", " us", 1),
    ("env_fresh_us", "residual `env.step`, mean of a fresh process's first 300 steps", " us", 1),
    ("env_mean_us", "residual `env.step`, mean over two episodes (resets included)", " us", 1),
    ("env_rand_us", "the same on `scenario=\"randomized\"` (with the law reference of each episode)", " us", 1),
    ("env_plain_us", "plain `env.step`, mean over two episodes", " us", 1),
    ("vec64", "vector env, residual, N = 64, 2 threads", " /s", 0),
)
"""``benchmarks/compare.py``'s figures in table order: key, row label, unit, decimals."""


def compare_table(name: str = "compare") -> str:
    """Two trees measured in interleaved rounds, medians and the range over rounds, from
    ``docs/speed/<name>.json`` (``python benchmarks/compare.py BASE_TREE . --json docs/speed/<name>.json``)."""
    d = _load("speed", f"{name}.json")
    commits = {k: d["trees"][k]["commit"] or d["trees"][k]["path"] for k in ("base", "new")}
    out = [f"| what | base ({commits['base']}) | new ({commits['new']}) | new / base | over rounds, base; new |",
           "|---|---|---|---|---|"]
    for key, label, unit, digits in COMPARE_ROWS:
        if key not in d["medians"]["base"] or key not in d["medians"]["new"]:
            continue  # a file from before the figure was measured
        b, n = d["medians"]["base"][key], d["medians"]["new"][key]
        spans = "; ".join(_span([r[key] for r in d["runs"][t]], _dec(digits)) for t in ("base", "new"))
        out.append(f"| {label} | {b:,.{digits}f}{unit} | {n:,.{digits}f}{unit} | {n / b:.2f}"
                   f"{' (speed)' if key == 'vec64' else ''} | {spans}{unit} |")
    return "\n".join(out) + f"\n\nMedians of {d['rounds']} interleaved rounds, {_measured(d)}.\n"


def threads_table() -> str:
    """A CleanRL-style loop's agent steps per second for pairs of env and torch threads, medians over
    rounds, from ``docs/speed/threads.json`` (``python benchmarks/bench_threads.py --json
    docs/speed/threads.json``)."""
    d = _load("speed", "threads.json")
    out = ["| env threads | torch threads | agent steps/s |", "|---|---|---|"]
    for p in d["pairs"]:
        env = f"{p['env_threads_used']}" + (" (the default)" if p["env_threads"] == "default" else "")
        torch = f"{p['torch_threads_used']}" + (" (torch's default)" if p["torch_threads"] == "default" else "")
        out.append(f"| {env} | {torch} | {p['steps_per_s']:,.0f} |")
    return "\n".join(out) + f"\n\n{d['num_envs']} arms, medians of {d['rounds']} rounds, {_measured(d)}.\n"


MEASURED_BLOCKS = (
    ("docs/speed.md", "speed", ("core", "env", "resets"), speed_table),
    ("docs/speed.md", "speed-compare", ("compare",), compare_table),
    ("docs/speed.md", "speed-compare-layout", ("compare_layout",), lambda: compare_table("compare_layout")),
    ("docs/conventions.md", "threads", ("threads",), threads_table),
)
"""The benchmark tables: page, marker name, the files under ``docs/speed/`` it needs, the function."""


FALSIFY_ROWS = (
    ("PPO residual over the law, no filter", "residual"),
    ("certified residual, `barrier`", "barrier"),
    ("certified residual, `barrier:handback=0.0033` (shipped)", "barrier_handback"),
    ("certified residual, `barrier:handback=0.0033,lookahead=0.35`", "barrier_handback_lookahead"),
    ("certified residual, `barrier:handback=0.0033,lookahead=0.35,predict=0.5`", "barrier_handback_predict"),
    ("certified residual, `cbf:handback=0.0033`", "cbf_handback"),
    ("certified residual, `cbf:handback=0.0033,lookahead=0.35`", "cbf_handback_lookahead"),
    ("PPC", "ppc"),
    ("funnel control", "funnel"),
    ("nonlinear MPC", "nmpc"),
)
"""The falsifier's rows (docs/falsify/run.sh): label, folder under docs/falsify."""


def falsify_table() -> str:
    """blf-falsify's reports (issue 52, items 3-4), one row per policy, from
    ``docs/falsify/<row>/falsify.json``: the share of searches that found a counterexample, the
    counterexamples, the simulations to each search's first, the lowest robustness per search
    (degrees; negative is a counterexample) and the wall clock. Rows not run yet are left out."""
    import json

    out = ["| policy | searches x simulations | admissible (the law keeps every bound) | falsification rate | "
           "counterexamples | simulations to the first, per search | lowest robustness per search (deg) | "
           "wall clock (min) |", "|---|---|---|---|---|---|---|---|"]
    for label, row in FALSIFY_ROWS:
        f = DOCS / "falsify" / row / "falsify.json"
        if not f.is_file():
            continue
        r = json.loads(f.read_text())
        runs = r["runs"]
        first = ", ".join("-" if x["first_counterexample_at"] is None else str(x["first_counterexample_at"])
                          for x in runs)
        low = ", ".join(f"{x['lowest_robustness_deg']:.3g}" for x in runs)
        out.append(f"| {label} | {r['searches']} x {r['budget_per_search']} | "
                   f"{sum(x['admissible'] for x in runs)} | {r['falsification_rate']:.2f} | {r['counterexamples']} | "
                   f"{first} | {low} | {r['wall_s'] / 60:.0f} |")
    return "\n".join(out) + "\n"


def falsify_regions() -> str:
    """Where each row's counterexamples lie, in words (issue 52, item 3): the range of every knob over
    them, the law alone's margin there and how far beyond a bound the policy went."""
    import json

    out = []
    for label, row in FALSIFY_ROWS:
        f = DOCS / "falsify" / row / "falsify.json"
        if not f.is_file():
            continue
        ces = [c for run in json.loads(f.read_text())["runs"] for c in run["counterexamples"]]
        if not ces:
            out.append(f"- {label}: no counterexample.")
            continue
        knobs = []
        for k in ces[0]["params"]:
            if k == "noise_seed":
                continue
            v = [c["params"][k] for c in ces]
            knobs.append(f"{k} {min(v):.3g} to {max(v):.3g}" if min(v) != max(v) else f"{k} {v[0]:.3g}")
        law = [c["law_margin_deg"] for c in ces]
        pol = [-c["policy_margin_deg"] for c in ces]
        out.append(f"- {label}: {len(ces)} counterexample(s), at {', '.join(knobs)}; the law alone keeps "
                   f"{min(law):.2g} to {max(law):.2g} degrees there, the policy goes {min(pol):.2g} to "
                   f"{max(pol):.2g} degrees beyond the bound.")
    return "\n".join(out) + "\n"


BLOCKS: dict[str, dict[str, Callable[[], str]]] = {
    "README.md": {"headline": lambda: headline_table("docs/"), "verdict": lambda: verdict_table("docs/"),
                  "best-verdict": lambda: best_verdict("  ")},
    "docs/reproduction.md": {"reproduction": reproduction_table},
    "docs/results.md": {
        "headline": lambda: headline_table(here="results.md"),
        "family-headline": family_headline_table,
        "verdict": verdict_table,
        "protocol": protocol_table,
        "seed-statistics": lambda: statistics_table("", ("proposed", "ppo_residual", "bc", "lesobc"),
                                                    "seeds_report.json"),
        "seeds": seeds_table,
        "certified-statistics": lambda: statistics_rows_table(CERTIFIED_ROWS),
        "learners": learners_table,
        "best": best_table,
        "best-verdict": best_verdict,
    },
    "docs/environment.md": {
        "env-arguments": _env("arguments_table"),
        "env-observation": _env("observation_table", False),
        "env-reward-terms": _env("reward_terms_table"),
        "env-info": _env("info_table"),
    },
    "docs/tuning.md": {
        "oracle": oracle_table,
        "round1": tuning_round1_table,
        "round2": tuning_round2_table,
        "observation-variants": observation_variants_table,
    },
    "docs/budget.md": {"lagrangian-presets": lagrangian_presets_table,
                       "scale-statistics": lambda: statistics_table("budget/protocol_scale", ("proposed", "sbx_ppo_256")),
                       "sac-statistics": lambda: statistics_table("budget/protocol_sac", ("proposed", "sbx_sac")),
                       "fused-rounds": fused_rounds_table,
                       "warm-statistics": lambda: statistics_table("budget/protocol_warm",
                                                                   ("proposed", "ppo_lagrangian_warm", "ppo_warm")),
                       "residual-rates": residual_rates_table,
                       "offpolicy-select": lambda: statistics_table("budget/offpolicy_select",
                                                                    ("proposed", "sbx_sac", "sbx_crossq"))},
    "docs/levels.md": {"levels": levels_table, "floor": floor_table},
    "docs/family.md": {"family-members": family_members_table, "family-law": family_law_table,
                       "family-cost": family_cost_table, "family-protocol": family_protocol_table,
                       "family-ppc-gains": family_ppc_gains_table,
                       "family-tuned-gains": lambda: family_ppc_gains_table("proposed"),
                       "family-headline": family_headline_table},
    "docs/sweeps.md": {"sweep-keys": sweep_keys_table, "scaling": sweep_scaling_table},
    "docs/plain_search.md": {"searches": plain_search_table},
    "docs/lagrangian.md": {"hyperparameters": lagrangian_hyperparameters_table},
    "docs/extending.md": {"signals": signals_table},
    "docs/certificate.md": {"certificate-cases": certificate_cases_table, "certified-seeds": certified_seeds_table},
}
"""Page (from the repository's root) -> marker name -> the function that writes its table."""

if (DOCS / "ladder" / "L3" / "report.json").is_file():  # until the ladder has been scored
    BLOCKS["docs/levels.md"]["ladder"] = ladder_table
    BLOCKS["README.md"]["ladder-verdict"] = lambda: ladder_verdict("  ")
if any((DOCS / "falsify" / row / "falsify.json").is_file() for _, row in FALSIFY_ROWS):  # until a row has run
    BLOCKS["docs/certificate.md"]["falsify"] = falsify_table
    BLOCKS["docs/certificate.md"]["falsify-regions"] = falsify_regions
if (DOCS / "plain_audit" / "summary.json").is_file():  # until the audit has run, its page says so
    BLOCKS["docs/plain_audit.md"] = {"audit": audit_table}

for _page, _name, _files, _make in MEASURED_BLOCKS:
    if all((DOCS / "speed" / f"{f}.json").is_file() for f in _files):  # until then the table stays typed
        BLOCKS.setdefault(_page, {})[_name] = _make


def fill(text: str, name: str, content: str, where: str = "") -> str:
    """``text`` with the block between ``name``'s markers replaced by ``content``."""
    pattern = re.compile(rf"(<!-- begin:{re.escape(name)} -->\n).*?(<!-- end:{re.escape(name)} -->)", re.S)
    if not pattern.search(text):
        raise ValueError(f"{where}: no <!-- begin:{name} --> ... <!-- end:{name} --> markers")
    return pattern.sub(lambda m: m.group(1) + content.rstrip("\n") + "\n" + m.group(2), text, count=1)


def pages() -> dict[Path, str]:
    """Every page this command writes, with the text it would write."""
    out: dict[Path, str] = {}
    for rel, blocks in BLOCKS.items():
        path = ROOT / rel
        text = path.read_text()
        for name, make in blocks.items():
            text = fill(text, name, make(), rel)
        out[path] = text
    out.update(CONTROL.pages())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python docs/tables.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a page differs")
    args = ap.parse_args(argv)
    stale = []
    for path, text in pages().items():
        old = path.read_text() if path.exists() else None
        if old != text:
            stale.append(path.relative_to(ROOT))
            if not args.check:
                path.write_text(text)
    verb = "differ from what python docs/tables.py writes" if args.check else "rewritten"
    for p in stale:
        print(f"{p}: {verb}")
    if not stale:
        print("every generated table is up to date")
    return 1 if (stale and args.check) else 0


if __name__ == "__main__":
    sys.exit(main())

"""Every generated table of the README and the documentation, rewritten by one command:

    python docs/tables.py            # rewrite them all
    python docs/tables.py --check    # exit 1, naming each file, if any differs (no writes)

A generated table sits between ``<!-- begin:NAME -->`` and ``<!-- end:NAME -->`` in its page and
is made either from the code's own declarations (the env's arguments, observation, reward terms
and info keys) or from a results file in ``docs/`` (never typed by hand). The control side's
pages are written whole by ``docs/control/tables.py``, which this command runs too.
``tests/test_docs_tables.py`` fails when anything here differs from what it would write.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import sys
from pathlib import Path
from typing import Any, Callable

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent


def _module(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _env(name: str, *args: object) -> Callable[[], str]:
    """The table that ``blf_gym.env.<name>(*args)`` makes (imported when asked for)."""
    def make() -> str:
        from blf_gym import env

        return getattr(env, name)(*args)

    return make


HEADLINE = (
    # label, kind, results file under docs/, policy name there, the page with its full table
    ("proposed law (LESO + BLF, the paper's gains)", "control, certified", "protocol_control", "proposed",
     "control/protocol.md"),
    ("BC (the paper's)", "control", "protocol_control", "bc", "control/protocol.md"),
    ("LESOBC (the paper's)", "control", "protocol_control", "lesobc", "control/protocol.md"),
    ("prescribed-performance control", "control", "protocol_control", "ppc", "control/protocol.md"),
    ("funnel control", "control", "protocol_control", "funnel", "control/protocol.md"),
    ("nonlinear MPC", "control", "nmpc", "nmpc", "control/nmpc.md"),
    ("PPO residual over the law (seed 0 of 5)", "learning + law", "protocol_learners", "ppo_residual",
     "results.md"),
    ("PPO residual, barrier-filtered (seed 0 of 5)", "learning + law", "protocol_learners",
     "ppo_residual_certified", "results.md"),
    ("plain PPO, searched (best plain learner)", "learning", "protocol_learners", "ppo_plain_searched",
     "plain_search.md"),
    ("PPO-Lagrangian", "learning", "protocol_learners", "ppo_lagrangian", "lagrangian.md"),
)
"""The headline comparison's rows: one per method, its shipped or best configuration."""

_GROUPS = ("paper-0.1hz", "paper-0.5hz", "randomized", "stress")
"""The protocol's four groups, in table order."""


def headline_table(prefix: str = "") -> str:
    """One row per method of :data:`HEADLINE`: ``score_vs_law`` on the presets, the training suite's
    held-out episodes and the stress suite (pooled RMSEs), the failure rates and the stress suite's
    ``certificate_broken``; links are ``prefix`` + the page (the README passes ``docs/``). A method
    whose results file is absent is left out."""
    cache: dict[str, list[dict]] = {}
    lines = ["| method | kind | score 0.1 Hz / 0.5 Hz | score, training suite | score, stress | "
             "failure rate, training / stress | certificate broken, stress | full table |",
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

        lines.append(f"| {label} | {kind} | {sc('paper-0.1hz')} / {sc('paper-0.5hz')} | {sc('randomized')} | "
                     f"{sc('stress')} | {rec['randomized']['failure_rate']:.2f} / {rec['stress']['failure_rate']:.2f} | "
                     f"{rec['stress']['certificate_broken']:.2f} | [{page}]({prefix}{page}) |")
    return "\n".join(lines) + "\n"


CONTROL = _module(DOCS / "control" / "tables.py")
"""docs/control/tables.py, which writes the control side's pages."""
GROUP_LABEL: dict[str, str] = CONTROL.GROUPS
"""A scenario group's label in the tables (the control pages' own)."""


def _load(folder: str, name: str = "results.json") -> Any:
    import json

    return json.loads((DOCS / folder / name).read_text())


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
    ``docs/protocol/results.json`` (the certified agent from ``docs/protocol_learners/``)."""
    main, learners = _load("protocol")["records"], _load("protocol_learners")["records"]
    rows = [("BC", main, "bc"), ("LESOBC", main, "lesobc"), ("proposed", main, "proposed"),
            ("**ppo_residual** (seed 0)", main, "ppo_residual_s0"),
            ("**ppo_residual_certified** (seed 0)", learners, "ppo_residual_certified"),
            ("ppo_plain", main, "ppo_plain")]
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
    ``statistics`` of ``python -m agents.report``'s JSON in ``docs/<folder>``."""
    stats = _load(folder, report)["statistics"]
    out = ["| policy | group | seeds x episodes | IQM score_vs_law [95 % CI] | P(improvement over the law) "
           "[95 % CI] | failure rate | certificate_broken |", "|---|---|---|---|---|---|---|"]
    for g in _GROUPS:
        for policy in policies:
            st = next(x for x in stats if x["policy"] == policy and x["scenario"] == g)
            label = GROUP_LABEL[g] if g.startswith("paper") else f"{GROUP_LABEL[g]} ({st['episodes']})"
            out.append(f"| {policy} | {label} | {len(st['seeds'])} x {st['episodes']} | {_ci(st, 'iqm', 3)} | "
                       f"{_ci(st, 'prob_improvement', 2)} | {st['failure_rate']:.2f} | "
                       f"{st['certificate_broken']:.2f} |")
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


BLOCKS: dict[str, dict[str, Callable[[], str]]] = {
    "README.md": {"headline": lambda: headline_table("docs/")},
    "docs/reproduction.md": {"reproduction": reproduction_table},
    "docs/results.md": {
        "headline": headline_table,
        "protocol": protocol_table,
        "seed-statistics": lambda: statistics_table("", ("proposed", "ppo_residual", "bc", "lesobc"),
                                                    "seeds_report.json"),
        "seeds": seeds_table,
        "certified-statistics": lambda: statistics_table("protocol_certified",
                                                         ("proposed", "ppo_residual", "ppo_residual_certified")),
        "learners": learners_table,
    },
    "docs/environment.md": {
        "env-arguments": _env("arguments_table"),
        "env-observation": _env("observation_table", False),
        "env-reward-terms": _env("reward_terms_table"),
        "env-info": _env("info_table"),
    },
}
"""Page (from the repository's root) -> marker name -> the function that writes its table."""


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

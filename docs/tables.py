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
from typing import Callable

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


def headline_table(prefix: str = "") -> str:
    """One row per method of :data:`HEADLINE`: ``score_vs_law`` on the presets, the training suite's
    held-out episodes and the stress suite (pooled RMSEs), the failure rates and the stress suite's
    ``certificate_broken``; links are ``prefix`` + the page (the README passes ``docs/``). A method
    whose results file is absent is left out."""
    import json

    cache: dict[str, list[dict]] = {}
    lines = ["| method | kind | score 0.1 Hz / 0.5 Hz | score, training suite | score, stress | "
             "failure rate, training / stress | certificate broken, stress | full table |",
             "|---|---|---|---|---|---|---|---|"]
    for label, kind, folder, policy, page in HEADLINE:
        path = DOCS / folder / "results.json"
        if not path.is_file():
            continue
        if folder not in cache:
            cache[folder] = json.loads(path.read_text())["records"]
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


BLOCKS: dict[str, dict[str, Callable[[], str]]] = {
    "README.md": {"headline": lambda: headline_table("docs/")},
    "docs/results.md": {"headline": headline_table},
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
    control = _module(DOCS / "control" / "tables.py")
    out.update(control.pages())
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

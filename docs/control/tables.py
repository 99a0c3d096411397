"""The control side's tables, written from blf-eval's results files (never typed by hand).

    python docs/control/tables.py            # rewrites docs/control/protocol.md and filters.md

* ``protocol.md``: every controller on the protocol (the two presets, the training suite's 20
  held-out episodes, the stress suite's 50), from ``docs/protocol_control/results.json``, written by
  ``blf-eval --controllers bc lesobc proposed ppc funnel proposed_tuned pd_gravity pd_gravity_leso
  computed_torque computed_torque_leso --agents --out docs/protocol_control``.
* ``filters.md``: the shipped plain agents with no filter, the barrier filter and the CBF filter,
  from ``docs/filters_plain/<filter>/results.json``, written by ``blf-eval --agents
  agents/pretrained/ppo_plain agents/pretrained/ppo_plain_searched agents/pretrained/ppo_lagrangian
  --residual-filter <filter> --jobs 1 --out docs/filters_plain/<folder>`` for none, barrier and cbf,
  and barrier:handback=0.0033 and cbf:handback=0.0033 (folders barrier_handback, cbf_handback).
* ``nmpc.md``: the NMPC beside the proposed law on the protocol, with its solver's account (solve
  time per 10 ms sample, fallbacks), from ``docs/nmpc/results.json``, written by
  ``docs/nmpc/run.sh``.
"""

from __future__ import annotations

import json
from pathlib import Path

DOCS = Path(__file__).resolve().parent.parent
GROUPS = {"paper-0.1hz": "0.1 Hz", "paper-0.5hz": "0.5 Hz", "randomized": "training suite", "stress": "stress"}


def _records(path: Path) -> tuple[list[dict], str]:
    """A results file's records and the command that wrote it, its ``--out`` shown as ``OUT`` when
    that was a scratch folder outside the repository's ``docs/``."""
    import re

    data = json.loads(path.read_text())
    cmd = data["provenance"].get("command", "?")
    return data["records"], re.sub(r"--out (?!docs/)\S+", "--out OUT", cmd)


def _row(r: dict, name: str | None = None) -> str:
    rm = " | ".join(f"{v:.4g}" for v in r["rmse_deg"])
    score = "-" if r.get("score_vs_law") is None else f"{r['score_vs_law']:.3f}"
    cert = "-" if r.get("certificate_broken") is None else f"{r['certificate_broken']:.2f}"
    div = " (diverged)" if r.get("diverged") else ""
    return (f"| {name or r['policy']} | {GROUPS.get(r['scenario'], r['scenario'])} ({r['episodes']}) | {rm} | {score} | "
            f"{sum(r['violations']):,} | {r['failure_rate']:.2f}{div} | {cert} | {r['wall_s'] / r['episodes']:.2f} |")


HEAD = ("| policy | group (episodes) | RMSE j1 (deg) | j2 | j3 | score_vs_law | violating samples | failure rate | "
        "certificate_broken | wall s / episode |\n|---|---|---|---|---|---|---|---|---|---|")


def protocol_table() -> str:
    recs, cmd = _records(DOCS / "protocol_control" / "results.json")
    order = {g: i for i, g in enumerate(GROUPS)}
    recs = sorted(recs, key=lambda r: (order.get(r["scenario"], 9), r["policy"]))
    return (f"Written by `python docs/control/tables.py` from `docs/protocol_control/results.json` (`{cmd}`). "
            "Wall time per episode: the group's wall time over its episodes, two worker processes on this "
            "2-core machine, episodes batched.\n\n" + HEAD + "\n" + "\n".join(_row(r) for r in recs) + "\n")


FILTER_RUNS = ("none", "barrier", "barrier_handback", "cbf", "cbf_handback")
"""The folders of ``docs/filters_plain``, in the table's order within a policy and group: no filter,
each filter without and with the hand-back (``--residual-filter barrier:handback=0.0033``)."""


def filters_table() -> str:
    lines = []
    cmds = []
    for folder in FILTER_RUNS:
        path = DOCS / "filters_plain" / folder / "results.json"
        if not path.is_file():
            continue
        recs, cmd = _records(path)
        cmds.append(f"`{cmd}`")
        for r in recs:
            if r["kind"] == "baseline":
                continue
            base = r["policy"].split("+")[0].removesuffix("-filter")
            spec = r["env_kwargs"].get("residual_filter") or "none"  # the filter as the run named it
            lines.append((base, list(GROUPS).index(r["scenario"]) if r["scenario"] in GROUPS else 9,
                          FILTER_RUNS.index(folder), _row(r, f"{base}, filter {spec}")))
    lines.sort()
    return ("Written by `python docs/control/tables.py` from `docs/filters_plain/*/results.json` ("
            + "; ".join(cmds) + ").\n\n" + HEAD + "\n" + "\n".join(row for *_, row in lines) + "\n")


NMPC_RUNS = (("", "The real-time iteration (the default scheme)"),
             ("ipopt", "IPOPT to convergence (`scheme=\"ipopt\"`), the first protocol run"))
"""The NMPC's protocol runs under ``docs/nmpc``: folder and heading, the current scheme first."""


def nmpc_table(sub: str = "") -> str:
    """One NMPC protocol run's table, with the solver's account from its report."""
    path = DOCS / "nmpc" / sub / "results.json"
    recs, cmd = _records(path)
    order = {g: i for i, g in enumerate(GROUPS)}
    recs = sorted(recs, key=lambda r: (order.get(r["scenario"], 9), r["policy"]))
    rep = next((r["policy_report"] for r in recs if r.get("policy_report")), None)
    solver = ""
    if rep is not None:
        samples = rep.get("samples", rep["solves"])  # older reports solved at every sample
        skipped = samples - rep["solves"]
        solver = (f" The NMPC over all {samples:,} samples of the run: {rep['solves']:,} solves"
                  + (f" ({skipped:,} samples skipped while the fallback acted)" if skipped else "")
                  + f", each median {rep['solve_ms_median']:.1f} ms, 99th percentile {rep['solve_ms_p99']:.1f} ms, "
                  f"largest {rep['solve_ms_max']:.0f} ms per 10 ms sample (the estimator included); "
                  f"{rep['fallbacks']:,} samples on the fallback, {rep.get('estimator_restarts', 0):,} estimator "
                  "restarts; statuses " + ", ".join(f"{k} {v:,}" for k, v in sorted(rep["statuses"].items())) + ".")
    rel = path.relative_to(DOCS.parent).as_posix()
    return (f"Written by `python docs/control/tables.py` from `{rel}` (`{cmd}`, "
            "docs/nmpc/run.sh). Wall time per episode: the group's share of the batches' wall time over its "
            "episodes, the NMPC's two solver processes on this 2-core machine ([docs/model.md section 15]"
            "(../model.md#15-nonlinear-mpc-nmpc) says what else ran)." + solver + "\n\n"
            + HEAD + "\n" + "\n".join(_row(r) for r in recs) + "\n")


def nmpc_page() -> str:
    """Every NMPC protocol run found under ``docs/nmpc``, the current scheme first."""
    parts = [f"## {title}\n\n{nmpc_table(sub)}" for sub, title in NMPC_RUNS
             if (DOCS / "nmpc" / sub / "results.json").is_file()]
    return "\n".join(parts)


TITLES = {
    "protocol.md": ("The control side on the protocol",
                    "Every registered controller on the benchmark's protocol: the paper's laws, the proposed "
                    "law with tuned gains (`proposed_tuned`), prescribed-performance and funnel control, and "
                    "the classical PD with gravity compensation and computed torque, each full-state and on "
                    "the LESO ([the model](../model.md), sections 12, 13 and 16, gives their equations and how "
                    "their gains were chosen: one grid search, 40 points, the same 10 selection episodes and "
                    "torque budget for each; computed torque has no point within that budget, and runs at the "
                    "least torque that kept the bounds). `score_vs_law` is against the proposed law with the "
                    "paper's gains; a failure is an episode with a violation or a divergence."),
    "filters.md": ("Filters around the plain agents",
                   "The shipped plain agents (their whole torque from the network) with no filter, and through "
                   "the barrier and the CBF filter, each without and with the hand-back "
                   "([the certificate](../certificate.md) says what each filter guarantees)."),
    "nmpc.md": ("Nonlinear MPC on the protocol",
                "The NMPC policy ([the model, section 15](../model.md#15-nonlinear-mpc-nmpc)) beside the proposed "
                "law, with its solver's account. Its rows come from one named command, `docs/nmpc/run.sh`, since "
                "it is too slow for the main job's default set."),
}
"""Each page's title and first paragraph, above its generated tables."""


UNSEARCHED = {
    "bc": "the paper's gains (its Table 2), no search",
    "lesobc": "the paper's gains (its Table 2), no search",
    "proposed": "the paper's gains (its Table 2), no search: the yardstick",
    "nmpc": "horizon and weights set by hand while building it (docs/model.md section 15), no search",
}
"""How the controllers without a grid search got their gains."""


def tuning_table() -> str:
    """How every controller's gains were chosen: the grid search's size, selection episodes, torque
    budget and choice from ``docs/gains/NAME/gains.json`` (``python -m baselines.gains``), or how they
    were set without one."""
    rows = []
    for name, how in UNSEARCHED.items():
        rows.append(f"| `{name}` | {how} | - | - | - | - |")
    for path in sorted((DOCS / "gains").glob("*/gains.json")):
        d = json.loads(path.read_text())
        if "controller" not in d:
            continue  # a filter's search (docs/gains/cbf), not a controller's
        name = "proposed_tuned" if d["controller"] == "proposed" else d["controller"]
        sizes = d.get("grid_note") or " x ".join(f"{len(v)} {k}" for k, v in d["grid"].items())
        points = len(d["rows"])  # every point evaluated
        chosen = d.get("chosen")
        keeping = [r for r in d["rows"] if not r["failed_on"]]
        if chosen and d.get("chosen_keeps_bounds", True):
            pick = ", ".join(f"{k} = {v:g}" for k, v in chosen.items())
        elif chosen:
            row = next(r for r in d["rows"] if r["point"] == chosen)
            pick = (", ".join(f"{k} = {v:g}" for k, v in chosen.items()) + ", the best score within the budget: "
                    f"no point kept every bound (it breaks one on {len(row['failed_on'])} of {len(d['episodes'])})")
        elif keeping:
            least = min(keeping, key=lambda r: r["effort_ratio"])
            pick = ("none within the budget: it runs at the point that kept every bound with the least torque, "
                    + ", ".join(f"{k} = {v:g}" for k, v in least["point"].items())
                    + f" ({least['effort_ratio']:.2f} x)")
        else:
            pick = "none: no point kept every bound on the selection episodes (it runs at its defaults)"
        rows.append(f"| `{name}` | grid search, `docs/gains/{path.parent.name}/` ({sizes}) | {points} | "
                    f"{len(d['episodes'])} | {d['effort']:g} x the paper-gain law's RMS torque | {pick} |")
    return ("How each controller's gains were chosen (the same search, selection episodes and torque budget for "
            "every searched law; never a held-out or stress episode), written from `docs/gains/*/gains.json`:\n\n"
            "| controller | how | candidate points | selection episodes | torque budget | chosen |\n"
            "|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")


FALSIFIED = (("ppc", "prescribed-performance control"), ("funnel", "funnel control"), ("nmpc", "nonlinear MPC"))
"""The control rows the falsifier searched (docs/falsify/run.sh): folder, label."""


def falsify_control_table() -> str:
    """Where each control row breaks a bound that the proposed law with the paper's gains keeps, from
    blf-falsify's reports (``docs/falsify/<row>/falsify.json``); "" until one exists."""
    import json

    rows = []
    for row, label in FALSIFIED:
        f = DOCS / "falsify" / row / "falsify.json"
        if f.is_file():
            r = json.loads(f.read_text())
            low = min(x["lowest_robustness_deg"] for x in r["runs"])
            rows.append(f"| {label} | {r['searches']} x {r['budget_per_search']} | {r['falsification_rate']:.2f} | "
                        f"{r['counterexamples']} | {low:.3g} |")
    if not rows:
        return ""
    return ("Where each breaks a bound that the law with the paper's gains keeps, searched by `blf-falsify` over "
            "`SAFE_RANGES` (`docs/falsify/run.sh`; the regions are in [the certificate](../certificate.md#judged-by-"
            "the-falsifier)):\n\n| controller | searches x simulations | falsification rate | counterexamples | "
            "lowest robustness (deg) |\n|---|---|---|---|---|\n" + "\n".join(rows) + "\n")


def _page(name: str, body: str) -> str:
    title, lead = TITLES[name]
    return f"# {title}\n\n{lead}\n\n{body}"


def pages() -> dict[Path, str]:
    """Every page this script writes, with its text (a page whose results are absent is left out)."""
    out = DOCS / "control"
    falsified = falsify_control_table()
    made = {out / "protocol.md": _page("protocol.md", protocol_table() + "\n" + tuning_table()
                                       + ("\n" + falsified if falsified else ""))}
    if (DOCS / "filters_plain").is_dir():
        made[out / "filters.md"] = _page("filters.md", filters_table())
    if (DOCS / "nmpc" / "results.json").is_file():
        made[out / "nmpc.md"] = _page("nmpc.md", nmpc_page())
    return made


def main() -> None:
    made = pages()
    for path, text in made.items():
        path.write_text(text)
    print("wrote " + ", ".join(str(p) for p in made))


if __name__ == "__main__":
    main()

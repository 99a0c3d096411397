"""Choose a controller's gains on a grid, reading only the paper's presets and training-suite draws.

    python -m baselines.gains ppc --grid K1=10,20,40 --grid K2=22.5,45,90 --out docs/gains/ppc
    python -m baselines.gains funnel --grid k_u=5,10,20,40 --out docs/gains/funnel

Every point of the grid (the product of the ``--grid`` lists; a scalar given for a per-joint gain
scales the paper's vector, see :func:`candidate_kwargs`) runs the two presets and ``--episodes``
draws of the training suite with *training* seeds 0, 1, ... (the protocol's held-out seeds start at
10,000 and the stress suite is never read). A point that breaks a bound or diverges on any of them
is out, and so is one whose RMS torque exceeds ``--effort`` times the proposed law's on any of them
(a high-gain law buys its tracking with torque: under the suite's measurement noise it chatters). The
rest are ranked by the geometric mean of their ``score_vs_law`` against the proposed law on the same
episodes (higher is better). The table goes to ``OUT/gains.md`` and every number to
``OUT/gains.json``, both written atomically with the command that produced them.

With ``--filter NAME`` the grid is over a residual filter of the proposed law instead (e.g.
``--filter cbf --grid gamma1=100,200,400 --grid gamma2=...``, or ``--grid gamma=...`` for both of
the CBF's rates): each point runs the law through the filter with a zero residual, and the chosen
point is the first, in the order the grid lists them (most restrictive first), whose filter leaves
the law's own episodes untouched (the same RMSE to the last bit on every one), so that the law
with the filter is the law.

With ``--n-links N`` the search is on the task family's member of N links (docs/family.md): its
two presets and its training draws, every law (the candidate and the proposed law it is scored
against) on its arm, and a scalar for a per-joint gain scales the vector carried to that arm.

A grid of a few points is enumerated directly: each point is one batched kernel call of a few
episodes, and a sweep library's scheduler would add nothing but start-up time.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.results.io import atomic_write_text, help_text
from blf_gym.results.metrics import episode_stats, provenance, score_vs_law
from blf_gym.model.family import PAPER_LINKS, check_n_links, family_arm, family_base, family_preset, family_presets
from blf_gym.plugins.registry import available_controllers, make_controller, make_observer
from blf_gym.envs.scenarios import sample_suite
from blf_gym.kernel.simulate import simulate_batch

__all__ = ["candidate_kwargs", "selection_scenarios", "evaluate_gains", "evaluate_filter", "main"]


def selection_scenarios(episodes: int, n_links: int = PAPER_LINKS) -> list[tuple[str, Any]]:
    """(label, scenario): the two presets, then ``episodes`` training-suite draws from training seeds
    0 .. episodes - 1; of the task family's member of ``n_links`` links (blf_gym.model.family), the
    paper's by default."""
    out = [(name, family_preset(name)) for name in family_presets(n_links)]
    base = family_base(n_links)
    out += [(f"randomized/{k}", sample_suite(np.random.default_rng(k), base, "randomized")) for k in range(episodes)]
    return out


def _law(name: str, n_links: int, **kwargs: Any) -> Any:
    """The controller ``name`` for the member of ``n_links`` links: on another arm than the paper's,
    built on it, its defaults carried (baselines.params)."""
    if n_links == PAPER_LINKS:
        return make_controller(name, **kwargs)
    return make_controller(name, nominal=family_arm(n_links), **kwargs)


def candidate_kwargs(controller: str, point: dict[str, float], n_links: int = PAPER_LINKS) -> dict[str, Any]:
    """The factory's keyword arguments for one grid point: a scalar for a per-joint (tuple) gain
    multiplies the default vector by value / its first entry, so ``K1=40`` means the paper's
    K1 = (20, 20, 15) scaled to (40, 40, 30); any other gain is passed as it is. On another member
    of the task family (``n_links``) the vector scaled is the law's default carried to that arm."""
    defaults = _law(controller, n_links).params
    kw: dict[str, Any] = {}
    for k, v in point.items():
        d = getattr(defaults, k, None)
        if d is None:
            raise ValueError(f"--grid {k}: the {controller} law has no gain {k!r}")
        kw[k] = tuple(float(v) * x / d[0] for x in d) if isinstance(d, tuple) else float(v)
    return kw


def _rmse_and_failure(controller: Any, scenarios: Sequence[Any], residual_filter: Any = None,
                      observer: Any = "leso") -> list[tuple[list[float] | None, bool, float]]:
    """Per scenario: the per-joint RMSE (degrees), whether the episode failed, the RMS torque (N m,
    the root of the mean over samples of |u|^2). With ``residual_filter``, through that filter with
    a zero residual."""
    out = []
    by_duration: dict[float, list[int]] = {}
    for i, sc in enumerate(scenarios):
        by_duration.setdefault(sc.sim.duration, []).append(i)
    res: dict[int, Any] = {}
    for idx in by_duration.values():
        zero = None if residual_filter is None else np.zeros((len(idx), scenarios[idx[0]].arm.n_links))
        trajs = simulate_batch([scenarios[i] for i in idx], controller, observer, noise_seeds=idx, residual=zero,
                               residual_filter=residual_filter)
        for i, tr in zip(idx, trajs):
            st = episode_stats(tr)
            u_rms = float(np.sqrt(np.sum(st.u_sq) / st.samples)) if st.samples else float("inf")
            res[i] = (st.rmse_deg, st.failed, u_rms)
    for i in range(len(scenarios)):
        out.append(res[i])
    return out


def evaluate_gains(controller: str, grid: dict[str, list[float]], episodes: int = 8, effort: float = 1.25,
                   progress: bool = True, n_links: int = PAPER_LINKS) -> dict[str, Any]:
    """Every grid point's per-episode RMSE, failures, torque and geometric-mean score against the
    proposed law (see the module docstring); the points ranked, the chosen one first. On another
    member of the task family (``n_links``), its presets and training draws, every law on its arm."""
    from tqdm import tqdm

    labelled = selection_scenarios(episodes, n_links)
    scenarios = [sc for _, sc in labelled]
    obs = "leso" if n_links == PAPER_LINKS else make_observer("leso", nominal=family_arm(n_links))
    law = _rmse_and_failure(_law("proposed", n_links), scenarios, observer=obs)
    keys = list(grid)
    points = [dict(zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))]
    rows = []
    for point in tqdm(points, desc=f"{controller} gains", disable=not progress, file=sys.stderr):
        kw = candidate_kwargs(controller, point, n_links)
        res = _rmse_and_failure(_law(controller, n_links, **kw), scenarios, observer=obs)
        scores = [score_vs_law(r, lr) for (r, _, _), (lr, _, _) in zip(res, law)]
        failed = [lab for (lab, _), (_, f, _) in zip(labelled, res) if f]
        ratio = max(u / lu for (_, _, u), (_, _, lu) in zip(res, law))
        ok = not failed and ratio <= effort
        geo = float(np.exp(np.mean(np.log(np.maximum(scores, 1e-12)))))
        rows.append({"point": point, "kwargs": kw, "failed_on": failed, "effort_ratio": ratio, "admissible": ok,
                     "score_geomean": geo, "rmse_deg": {lab: r for (lab, _), (r, _, _) in zip(labelled, res)}})
    rows.sort(key=lambda r: (not r["admissible"], -r["score_geomean"]))
    return {"controller": controller, "n_links": n_links, "grid": grid, "effort": effort,
            "presets": list(family_presets(n_links)), "episodes": [lab for lab, _ in labelled],
            "law_rmse_deg": {lab: r for (lab, _), (r, _, _) in zip(labelled, law)},
            "law_u_rms": {lab: u for (lab, _), (_, _, u) in zip(labelled, law)},
            "law_failed_on": [lab for (lab, _), (_, f, _) in zip(labelled, law) if f],
            "chosen": rows[0]["point"] if rows and rows[0]["admissible"] else None, "rows": rows}


def _filter_kwargs(point: dict[str, float]) -> dict[str, float]:
    kw = dict(point)
    if "gamma" in kw:
        g = kw.pop("gamma")
        kw.update(gamma1=g, gamma2=g)
    return kw


def evaluate_filter(name: str, grid: dict[str, list[float]], episodes: int = 8,
                    progress: bool = True) -> dict[str, Any]:
    """Every grid point of the proposed law's filter ``name`` (see the module docstring): the
    episodes it alters with a zero residual, and its violations; the first untouched point chosen."""
    from tqdm import tqdm

    labelled = selection_scenarios(episodes)
    scenarios = [sc for _, sc in labelled]
    law_ctrl = make_controller("proposed")
    law = _rmse_and_failure(law_ctrl, scenarios)
    keys = list(grid)
    points = [dict(zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))]
    rows = []
    for point in tqdm(points, desc=f"{name} filter", disable=not progress, file=sys.stderr):
        filt = law_ctrl.filters[name](**_filter_kwargs(point))
        res = _rmse_and_failure(law_ctrl, scenarios, filt)
        altered = [lab for (lab, _), (r, _, _), (lr, _, _) in zip(labelled, res, law) if r != lr]
        failed = [lab for (lab, _), (_, f, _) in zip(labelled, res) if f]
        rows.append({"point": point, "kwargs": _filter_kwargs(point), "altered": altered, "failed_on": failed,
                     "admissible": not altered and not failed,
                     "rmse_deg": {lab: r for (lab, _), (r, _, _) in zip(labelled, res)}})
    chosen = next((r["point"] for r in rows if r["admissible"]), None)
    return {"filter": name, "grid": grid, "episodes": [lab for lab, _ in labelled], "chosen": chosen,
            "law_rmse_deg": {lab: r for (lab, _), (r, _, _) in zip(labelled, law)}, "rows": rows}


def filter_table(result: dict[str, Any]) -> str:
    """The filter's grid, in the order given, as a Markdown table."""
    keys = list(result["grid"])
    lines = [f"The proposed law through its `{result['filter']}` filter with a zero residual, on "
             f"{len(result['episodes'])} selection episodes (the two presets and training-suite seeds "
             f"0-{len(result['episodes']) - 3}). Chosen: the first point, most restrictive first, that leaves "
             "every episode as the law alone runs it: "
             + (", ".join(f"{k} = {v:g}" for k, v in result["chosen"].items()) if result["chosen"] else "none") + ".",
             "", "| " + " | ".join(keys) + " | episodes altered | failed on |", "|" + "---|" * (len(keys) + 2)]
    for r in result["rows"]:
        failed = ", ".join(r["failed_on"][:4]) + (f" (+{len(r['failed_on']) - 4})" if len(r["failed_on"]) > 4 else "")
        lines.append("| " + " | ".join(f"{r['point'][k]:g}" for k in keys)
                     + f" | {len(r['altered'])} of {len(result['episodes'])} | {failed or 'none'} |")
    return "\n".join(lines) + "\n"


def table(result: dict[str, Any]) -> str:
    """The ranked grid as a Markdown table."""
    keys = list(result["grid"])
    n = result.get("n_links", PAPER_LINKS)
    arm = "" if n == PAPER_LINKS else f" on the task family's {n}-link arm"
    lines = [f"Gains of the `{result['controller']}` law{arm} on {len(result['episodes'])} selection episodes "
             f"(the two presets and training-suite seeds 0-{len(result['episodes']) - 3}). Score: geometric "
             "mean of `score_vs_law` against the proposed law (higher is better); a point that breaks a "
             "bound or diverges anywhere is out, and so is one whose RMS torque exceeds "
             f"{result['effort']:g} times the law's on any episode (effort: the largest such ratio). Chosen: "
             + (", ".join(f"{k} = {v:g}" for k, v in result["chosen"].items()) if result["chosen"] else "none") + ".",
             "", "| " + " | ".join(keys) + " | score | effort | worst-joint RMSE, 0.1 Hz / 0.5 Hz (deg) | failed on |",
             "|" + "---|" * (len(keys) + 4)]
    for r in result["rows"]:
        rm = r["rmse_deg"]
        worst = " / ".join("-" if rm[p] is None else f"{max(rm[p]):.4g}"
                           for p in result.get("presets", ("paper-0.1hz", "paper-0.5hz")))
        score = f"{r['score_geomean']:.3f}" + ("" if r["admissible"] else " (out)")
        failed = ", ".join(r["failed_on"][:4]) + (f" (+{len(r['failed_on']) - 4})" if len(r["failed_on"]) > 4 else "")
        lines.append("| " + " | ".join(f"{r['point'][k]:g}" for k in keys) + f" | {score} | {r['effort_ratio']:.2f} | {worst} | {failed or 'none'} |")
    return "\n".join(lines) + "\n"


def _parse_grid(items: Sequence[str]) -> dict[str, list[float]]:
    grid: dict[str, list[float]] = {}
    for item in items:
        name, sep, values = item.partition("=")
        try:
            vals = [float(v) for v in values.split(",")] if sep else []
        except ValueError:
            vals = []
        if not name.isidentifier() or not vals:
            raise ValueError(f"--grid {item!r}: expected NAME=V1,V2,... (numbers)")
        grid[name] = vals
    return grid


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m baselines.gains", description=help_text(__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("controller", help="a registered controller (default: none, it must be given; with --filter, "
                                      "proposed)")
    p.add_argument("--filter", default=None, metavar="NAME",
                   help="grid over this residual filter of the proposed law instead of the controller's gains "
                        "(default: none)")
    p.add_argument("--grid", action="append", default=[], metavar="NAME=V1,V2",
                   help="a gain and its values (repeatable; default: none, at least one is needed)")
    p.add_argument("--episodes", type=int, default=8, metavar="N",
                   help="training-suite draws besides the two presets (default 8)")
    p.add_argument("--n-links", type=int, default=PAPER_LINKS, metavar="N",
                   help="the task family's member to choose the gains on (2 to 7 links, docs/family.md): its presets "
                        "and training draws, every law on its arm; the grid scales the gains carried to it (default 3, "
                        "the paper's arm)")
    p.add_argument("--effort", type=float, default=1.25, metavar="X",
                   help="largest admissible RMS torque, as a multiple of the proposed law's on the same episode "
                        "(default 1.25)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="folder for gains.md and gains.json (default: print the table only)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.controller not in available_controllers() or args.controller == "none":
            raise ValueError(f"unknown controller {args.controller!r}; accepted: {available_controllers()[1:]}")
        grid = _parse_grid(args.grid)
        if not grid:
            raise ValueError("give at least one --grid NAME=V1,V2,...")
        if not (args.effort > 0 and np.isfinite(args.effort)):
            raise ValueError(f"--effort must be a finite number > 0, got {args.effort}")
        if args.episodes < 0:
            raise ValueError(f"--episodes must be >= 0, got {args.episodes}")
        check_n_links("--n-links:", args.n_links)
        if args.filter is not None and args.n_links != PAPER_LINKS:
            raise ValueError("--filter searches the paper's arm only (give --n-links 3 or leave it out)")
        points = [dict(p) for p in itertools.product(*(((k, v) for v in vs) for k, vs in grid.items()))]
        if args.filter is not None:
            filters = make_controller("proposed").filters
            if args.controller != "proposed" or args.filter not in filters:
                raise ValueError(f"--filter: the proposed law's filters are {sorted(filters)}, and the controller "
                                 f"must be proposed; got {args.controller!r}, {args.filter!r}")
            for point in points:  # refuse a bad parameter before any simulation
                filters[args.filter](**_filter_kwargs(point))
        else:
            for point in points:
                _law(args.controller, args.n_links, **candidate_kwargs(args.controller, point, args.n_links))
    except ValueError as exc:
        print(f"python -m baselines.gains: error: {exc}", file=sys.stderr)
        return 2
    if args.filter is not None:
        result = evaluate_filter(args.filter, grid, args.episodes, progress=not args.no_progress)
        text = filter_table(result)
    else:
        result = evaluate_gains(args.controller, grid, args.episodes, args.effort, progress=not args.no_progress,
                                n_links=args.n_links)
        text = table(result)
    print(text, end="")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        command = "python -m baselines.gains " + " ".join(sys.argv[1:] if argv is None else argv)
        result["provenance"] = provenance(command)
        atomic_write_text(args.out / "gains.md", text)
        atomic_write_text(args.out / "gains.json", json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

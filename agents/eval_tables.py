"""blf-eval's printed table (:func:`table`, its legend :data:`LEGEND`) and its figures
(:func:`plots`: each group's tracking error with its bounds, and its torque)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.envs.protocol import (CURVE_GROUPS, EVAL_SEED_OFFSET, PROTOCOL_SEEDS, REFERENCE, SUITES,  # noqa: F401 (re-exported)
                                   suite_seed_offset)

# the one agent loader, re-exported here

__all__ = ["PlotTrace", "TABLE_NAME_MAX", "table", "PLOT_STYLES", "plots", "LEGEND"]



class PlotTrace:
    """What the plots draw of a group's first episode (time, error, bounds, torque), kept instead of
    the whole trajectory: a third of its memory, for every policy and group."""

    def __init__(self, tr: Any) -> None:
        self.t, self.e1, self.k_a, self.k_b, self.u = tr.t, tr.e1, tr.k_a, tr.k_b, tr.u
        self.n_samples = tr.n_samples


TABLE_NAME_MAX = 28
"""The widest policy name blf-eval's table prints whole; a longer one keeps its start and end
around an ellipsis (results.json has every name whole)."""


def _fit(name: str, width: int = TABLE_NAME_MAX) -> str:
    if len(name) <= width:
        return name
    head = (width - 1) // 2
    return name[:head] + "\u2026" + name[len(name) - (width - 1 - head):]


def _num(x: float | None, digits: int = 4) -> str:
    """A table number in at most 8 characters: fixed point while it fits, else 1.23e+04."""
    if x is None:
        return "-"
    for p in range(digits, -1, -1):
        text = f"{x:.{p}f}"
        if len(text) <= 8 and (p >= 1 or abs(x) >= 100):
            return text
    return f"{x:.2e}"


def table(records: Sequence[dict[str, Any]]) -> str:
    """blf-eval's console table: one row per record, each column as wide as its widest entry (so
    long names, labels and five-digit RMSEs keep the columns aligned), groups split by ``|``. The
    last column, ``div``, says ``yes`` when an episode of the group diverged."""
    n = max((len(r["rmse_deg"]) for r in records), default=1)  # joints: a column each
    head = [["policy", "kind", "scenario", "ep"], ["RMSE j1", *(f"j{j + 1}" for j in range(1, n))], ["score"],
            ["viol", "frac", "fail", "cert"], ["CVaR"], ["excess", "margin"], ["1st viol"], ["u rms", "u peak"],
            ["div"]]
    rows = []
    for r in records:
        viol = sum(v for v in r["violations"] if v is not None)
        frac = max((v for v in r["violation_fraction"] if v is not None), default=0.0)
        exc = max((v for v in r["max_excursion_deg"] if v is not None), default=0.0)
        mar = min((v for v in r["min_margin_deg"] if v is not None), default=0.0)
        rows.append([
            [_fit(str(r["policy"])), r["kind"], r["scenario"], str(r["episodes"])],
            [_num(v) for v in r["rmse_deg"]] + ["-"] * (n - len(r["rmse_deg"])),
            [_num(r.get("score_vs_law"), 3)],
            [str(viol), f"{frac:.4f}", f"{r['failure_rate']:.2f}", _num(r.get("certificate_broken"), 2)],
            [_num(r["rmse_cvar_deg"])],
            [_num(exc, 3), _num(mar, 3)],
            [_num(r["first_violation_s"], 3)],
            ["/".join("-" if v is None else f"{v:.1f}" for v in r[k]) for k in ("torque_rms", "torque_peak")],
            ["yes" if r["diverged"] else "-"]])
    widths = [[max(len(x) for x in col) for col in zip(*(row[g] for row in [head, *rows]))]
              for g in range(len(head))]
    left = {(0, 0), (0, 1), (0, 2)}  # names and labels read from the left, numbers from the right

    def line(row: list[list[str]]) -> str:
        return " | ".join(" ".join(x.ljust(w) if (g, i) in left else x.rjust(w)
                                   for i, (x, w) in enumerate(zip(cells, widths[g])))
                          for g, cells in enumerate(row)).rstrip()

    lines = [line(head)]
    lines.append("-" * len(lines[0]))
    lines += [line(row) for row in rows]
    return "\n".join(lines)


PLOT_STYLES = ("-", "-.", ":", (0, (5, 1, 1, 1, 1, 1)))
"""Line styles the plots cycle through, one per policy with its colour, widest first: so policies
whose curves overlap still show each other's (the bounds are black dashes)."""


def _figure(sc: str, rows: list[tuple[dict[str, Any], Any]], kind: str) -> Any:
    """One PNG's figure: each joint's tracking error with its bounds (``kind="error"``, as the
    paper's Figures 6 and 10) or its torque, for the group's first episode of each policy. Plain
    agents get a column of their own (their errors are often tens of degrees and would flatten the
    others'; a registered policy, such as the NMPC, is drawn with the laws). Each policy has its own
    colour, line style and width (:data:`PLOT_STYLES`), and the legend sits below the axes, where it
    covers no curve or bound."""
    import matplotlib.pyplot as plt

    def learned_plain(r: dict[str, Any]) -> bool:  # a registered policy (the NMPC) is drawn with the laws
        return r["kind"] == "plain" and not r.get("registered_policy")

    extra = [w for w, k in (("residual agents", "residual"), ("policies", "policy")) if any(
        (x[0]["kind"] == k) if k == "residual" else bool(x[0].get("registered_policy")) for x in rows)]
    columns = [("laws" + "".join(f" and {w}" for w in extra), [x for x in rows if not learned_plain(x[0])]),
               ("plain agents (own scale)", [x for x in rows if learned_plain(x[0])])]
    columns = [c for c in columns if c[1]]
    n = rows[0][1].e1.shape[1]  # joints: one row of axes each
    fig, axes = plt.subplots(n, len(columns), figsize=(9 if len(columns) == 1 else 14, 7.6 * (n / 3)), sharex=True,
                             squeeze=False)
    names = [r["policy"] for r, _ in rows]
    for col, (title, members) in enumerate(columns):
        plain = learned_plain(members[0][0])
        for j in range(n):
            ax = axes[j, col]
            for r, tr in members:
                i = names.index(r["policy"])
                y = np.degrees(tr.e1[:, j]) if kind == "error" else tr.u[:, j]
                ax.plot(tr.t, y, color=f"C{i % 10}", ls=PLOT_STYLES[i % len(PLOT_STYLES)],
                        lw=max(0.8, 2.0 - 0.3 * i), label=r["policy"])
            if kind == "error":
                tr = members[0][1]
                ax.plot(tr.t, np.degrees(tr.k_a[:, j]), "k--", lw=0.9, label="bounds")
                ax.plot(tr.t, -np.degrees(tr.k_b[:, j]), "k--", lw=0.9)
                if not plain:
                    # zoom on the steady bounds (they start at 29-34 deg and decay to 1-2 deg)
                    ax.set_ylim(-3 * np.degrees(tr.k_b[-1, j]), 3 * np.degrees(tr.k_a[-1, j]))
                ax.set_ylabel(f"e1_{j + 1} (deg)")
            else:
                ax.set_ylabel(f"u_{j + 1} (N m)")
            ax.grid(alpha=0.3)
        axes[0, col].set_title(title, fontsize=9)
        axes[-1, col].set_xlabel("t (s)")
    labels: dict[str, Any] = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            labels.setdefault(lab, h)
    fig.suptitle(f"{sc}: {'tracking error and its bounds' if kind == 'error' else 'commanded torque'}"
                 + ("" if rows[0][0]["episodes"] == 1 else f" (first of {rows[0][0]['episodes']} episodes)"),
                 fontsize=11)
    ncol = min(len(labels), 6)
    fig.legend(list(labels.values()), list(labels), loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    rows_of_legend = -(-len(labels) // ncol)
    fig.tight_layout(rect=(0, 0.03 + 0.035 * rows_of_legend, 1, 1))
    return fig


def plots(results: list[tuple[dict[str, Any], list[Any]]], out: Path) -> list[Path]:
    """The PNGs of a blf-eval run: per scenario group, ``error_<group>.png`` and
    ``torque_<group>.png`` (:func:`_figure`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blf_gym.results.io import atomic_path

    written = []
    for sc in sorted({r["scenario"] for r, _ in results}):
        rows = [(r, trajs[0]) for r, trajs in results if r["scenario"] == sc and trajs and trajs[0].n_samples]
        if not rows:
            continue
        for kind in ("error", "torque"):
            fig = _figure(sc, rows, kind)
            path = out / f"{kind}_{sc}.png"
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=110, format="png")
            plt.close(fig)
            written.append(path)
    return written


LEGEND = (
    "RMSE per joint, pooled over the group's episodes, in degrees; score: score_vs_law, the geometric mean "
    "over joints of the law's RMSE over the policy's (1 = the law, higher is better), on the pooled RMSEs "
    "(per episode in results.json). viol: violating 1 ms samples summed over joints and episodes; frac: the "
    "worst joint's violating fraction; fail: share of episodes with a violation or divergence; cert: "
    "certificate_broken, the share of episodes where the policy violates and the law alone, on the same "
    "scenario and noise, does not. CVaR: mean RMSE (averaged over joints) of the worst half of the episodes; "
    "excess (largest distance beyond a bound) and margin (closest approach to a bound, negative when "
    "beyond): worst joint, in degrees; 1st viol: earliest violation (s); torques in N m per joint; div: yes "
    "when an episode's simulation diverged (results.json: diverged). Names longer than "
    f"{TABLE_NAME_MAX} characters are shortened here, not in results.json.")
"""The printed table's legend."""

"""Drawing of the arm for ``render()``; imported lazily so ``import blf_gym`` stays light.

Left: the arm in its plane, the reference circle, the end-effector path and the current target.
Right: each joint's error e1 between its bounds (-k_b, k_a), red when outside, on a symmetric
log scale (linear within +-0.01 deg), so that errors from 0.01 degrees up to the bounds' tens of
degrees can be read on one axis. The title names the controller, the mode and the scenario.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from blf_gym.model.bounds import error_bounds
from blf_gym.model.dynamics import joint_positions
from blf_gym.model.reference import joint_reference
from blf_gym.model.params import Scenario


class ArmRenderer:
    """Matplotlib (Agg) renderer returning RGB arrays; ``human=True`` also shows a window."""

    def __init__(self, scenario: Scenario, human: bool = False, size: tuple[int, int] = (640, 320)) -> None:
        import matplotlib

        if not human:
            matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure

        self.human = human
        self.scenario = scenario
        dpi = 80
        if human:
            import matplotlib.pyplot as plt

            self.fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
            plt.ion()
        else:
            self.fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        if not human:
            FigureCanvasAgg(self.fig)
        self.ax_arm = self.fig.add_axes((0.05, 0.08, 0.45, 0.85))
        self.ax_err = self.fig.add_axes((0.6, 0.12, 0.36, 0.78))

    def draw(self, core: Any, i: int, path: list[np.ndarray]) -> np.ndarray:
        sc = core.scenarios[i]
        n = core.n
        q = core.loop.X[i, :n]
        pts = joint_positions(q, sc.arm)
        path.append(pts[-1].copy())
        r = sc.reference
        th = np.linspace(0, 2 * np.pi, 200)
        ax = self.ax_arm
        ax.clear()
        ax.plot(r.center[0] + r.radius * np.cos(th), r.center[1] + r.radius * np.sin(th), "--",
                color="0.6", lw=1, label="reference")
        p = np.array(path)
        # the path so far (empty on an episode's first frame) and the end effector itself, on top
        # of the arm, so the legend's blue is on every frame
        ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.5, zorder=3)
        ax.plot(pts[:, 0], pts[:, 1], "-o", color="k", lw=3, ms=4)
        ax.plot(pts[-1, 0], pts[-1, 1], "o", color="tab:blue", ms=7, zorder=4, label="end effector and its path")
        t = float(core.loop.time[i])
        ax.plot(r.center[0] + r.radius * np.cos(2 * np.pi * r.frequency * t),
                r.center[1] + r.radius * np.sin(2 * np.pi * r.frequency * t), "x", color="tab:red")
        reach = float(np.sum(sc.arm.lengths))
        ax.set_xlim(-0.2, reach)
        ax.set_ylim(-0.45, 0.45)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        ctrl = core.controller.name
        who = f"residual over {ctrl}" if core.residual else "plain (agent torque)"
        ax.set_title(f"{sc.name} | {who} | t = {t:.2f} s", fontsize=8)
        ax.legend(loc="lower left", fontsize=7)
        ax2 = self.ax_err
        ax2.clear()
        # computed here, not through core.observe(), so drawing never consumes the env's RNG
        q_d = joint_reference(t, sc)[0]
        ka_r, kb_r = error_bounds(t, sc.bounds)
        e = np.degrees(q - q_d)
        ka, kb = float(np.degrees(ka_r)), float(np.degrees(kb_r))
        colors = ["tab:red" if (v >= ka or v <= -kb) else "tab:green" for v in e]
        ax2.bar(np.arange(1, n + 1), e, color=colors)
        ax2.axhline(ka, color="k", ls="--", lw=1)
        ax2.axhline(-kb, color="k", ls="--", lw=1)
        lim = 1.5 * max(ka, kb, float(np.max(np.abs(e))))
        ax2.set_yscale("symlog", linthresh=0.01, linscale=0.5)
        ax2.set_ylim(-lim, lim)
        ax2.axhline(0.0, color="0.5", lw=0.5)
        for j, v in enumerate(e):
            ax2.annotate(f"{v:+.3f}", (j + 1, v), ha="center", va="bottom" if v >= 0 else "top", fontsize=7)
        ax2.set_xticks(np.arange(1, n + 1))
        ax2.tick_params(labelsize=7)
        ax2.set_xlabel("joint", fontsize=8)
        ax2.set_ylabel("e1 (deg), symlog", fontsize=8)
        ax2.set_title("e1 within (-k_b, k_a), dashed", fontsize=8)
        self.fig.canvas.draw()
        frame = np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()
        if self.human:
            import matplotlib.pyplot as plt

            plt.pause(0.001)
        return frame

    def close(self) -> None:
        if self.human:
            import matplotlib.pyplot as plt

            plt.close(self.fig)

"""Per-arm layouts of one kernel call's integer status and of the last applied signals, declared once.

The kernel (:mod:`blf_gym.kernel.simulate`), the env (:mod:`blf_gym.envs.envcore`) and the reward
(:mod:`blf_gym.kernel.reward`) read their offsets from here.
"""

from __future__ import annotations

__all__ = ["STATUS_COLUMNS", "LAST_COLUMNS"]

STATUS_COLUMNS = ("steps", "diverged", "violating_steps", "first_violating_step", "saturated_steps",
                  "violating_samples", "filter_breaches", "assumption_failures")
"""Per-arm integer status of one kernel call: steps taken, divergence code (0, 1 non-finite or
beyond the limit, 2 numerically unstable, 3 a violation that ended the episode while the integration
was unstable), violating integration steps, the first one (global
index, -1 if none), steps with a saturated torque, violating 1 ms samples; with a residual filter,
the integration steps where its condition did not hold and where an assumption of its guarantee
failed (its ``breach`` and ``assumptions`` monitors, blf_gym.plugins.blocks.ResidualFilter)."""
(ST_STEPS, ST_DIVERGED, ST_VIOL_STEPS, ST_FIRST_VIOL, ST_SAT_STEPS, ST_VIOL_SAMPLES, ST_FILTER_BREACHES,
 ST_ASSUMPTION_FAILURES) = (STATUS_COLUMNS.index(c) for c in STATUS_COLUMNS)
N_STATUS = len(STATUS_COLUMNS)

LAST_COLUMNS = ("u", "u_law", "saturated", "x3", "x3_hat")
"""Per-arm, per-joint signals kept after a kernel call (``ClosedLoop.last``, n entries each): the
commanded torque, the law's torque and the saturation flag at the start of the last integration
step, the true lumped disturbance and the observer's x3_hat at the last 1 ms sample (NaN if the
observer has no x3_hat). The controller's outputs follow, in its declared order."""
LAST_U, LAST_ULAW, LAST_SAT, LAST_X3, LAST_X3HAT = (LAST_COLUMNS.index(c) for c in LAST_COLUMNS)
N_LAST = len(LAST_COLUMNS)

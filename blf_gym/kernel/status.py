"""The column indices of one kernel call's integer status and of the last applied signals, by name,
from their declarations in :mod:`blf_gym.jit.layout` (``STATUS``, ``LAST``).

The kernel (:mod:`blf_gym.kernel.simulate`), the env (:mod:`blf_gym.envs.envcore`) and the reward
(:mod:`blf_gym.kernel.reward`) read them from here.
"""

from __future__ import annotations

__all__ = ["STATUS_COLUMNS", "LAST_COLUMNS"]

from blf_gym.jit.layout import LAST, LAST_COLUMNS, STATUS, STATUS_COLUMNS

(ST_STEPS, ST_DIVERGED, ST_VIOL_STEPS, ST_FIRST_VIOL, ST_SAT_STEPS, ST_VIOL_SAMPLES, ST_FILTER_BREACHES,
 ST_ASSUMPTION_FAILURES) = (STATUS.index(c) for c in (
    "steps", "diverged", "violating_steps", "first_violating_step", "saturated_steps", "violating_samples",
    "filter_breaches", "assumption_failures"))
N_STATUS = len(STATUS)

# each LAST column is n long: its start is LAST_X * n
LAST_U, LAST_ULAW, LAST_SAT, LAST_X3, LAST_X3HAT = (LAST.start(c)[1] for c in ("u", "u_law", "saturated", "x3", "x3_hat"))
N_LAST = LAST.total[1]

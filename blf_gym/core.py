"""Deprecated: the batched env logic is :mod:`blf_gym.envcore` (its class ``EnvCore``), and the
observation's table is :mod:`blf_gym.observation`.

This module's name said nothing of what it held; it re-exports the same names so that code written
against it keeps working, and warns once on import.
"""

import warnings

from .envcore import *  # noqa: F403 (the env core's public names, unchanged)
from .envcore import __all__  # noqa: F401
from .observation import Entry  # noqa: F401 (the observation table's row, here before)

warnings.warn("blf_gym.core is deprecated; import from blf_gym.envcore (EnvCore, RewardWeights, MAX_ARMS, ...) or "
              "blf_gym.observation (OBSERVATION, Entry, observation_layout, ...)", DeprecationWarning, stacklevel=2)

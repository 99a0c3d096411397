"""Deprecated: the registry of controllers and observers is :mod:`blf_gym.registry`.

This module's name read like a controller; it re-exports the registry so that code written
against it keeps working, and warns once on import.
"""

import warnings

from .registry import *  # noqa: F403 (the registry's public names, unchanged)
from .registry import __all__  # noqa: F401

warnings.warn("blf_gym.controller is deprecated; import from blf_gym.registry (the same functions)",
              DeprecationWarning, stacklevel=2)

"""The paper's observer and control laws, and their packaging as blf_gym plug-ins.

* :mod:`baselines.leso` - the linear extended state observer (paper eqs. 8-10);
* :mod:`baselines.laws` - BC, LESOBC and the proposed LESO + barrier-Lyapunov law as pure compiled
  functions (Section 4.2, eqs. 16-21);
* :mod:`baselines.controllers` - gains dataclasses and the factories registered as the
  ``blf_gym.controllers`` / ``blf_gym.observers`` entry points;
* :mod:`baselines.reproduce` - the ``blf-reproduce`` command (Tables 3-4).

Imports point one way: ``baselines`` uses ``blf_gym``, never the reverse.
"""

from .controllers import ControllerGains, ObserverGains, bc, leso, lesobc, proposed

__all__ = ["ControllerGains", "ObserverGains", "bc", "lesobc", "proposed", "leso"]

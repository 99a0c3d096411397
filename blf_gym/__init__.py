"""blf-gym: the uncertain 3-DOF planar arm of Tran et al. (Electronics 2020, 9, 1355) with
time-varying output constraints, as a closed-loop simulator and a Gymnasium environment.

Modules: :mod:`~blf_gym.params` (parameters and presets), :mod:`~blf_gym.dynamics`,
:mod:`~blf_gym.uncertainty`, :mod:`~blf_gym.reference`, :mod:`~blf_gym.bounds`,
:mod:`~blf_gym.controller` (the plug-in protocol), :mod:`~blf_gym.simulate` (the compiled closed
loop), :mod:`~blf_gym.metrics`.
"""

from .params import PRESETS, Scenario, preset

__version__ = "0.1.0"
__all__ = ["PRESETS", "Scenario", "preset", "__version__"]

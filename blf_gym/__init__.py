"""blf-gym: the uncertain 3-DOF planar arm of Tran et al. (Electronics 2020, 9, 1355) with
time-varying output constraints, as a closed-loop simulator and a Gymnasium environment.

Importing the package registers ``PlanarBLF-v0`` (plain: the action is the torque) and
``PlanarBLFResidual-v0`` (residual over the LESO + barrier-Lyapunov law), both with a native
vector entry point for ``gym.make_vec``.

Modules: :mod:`~blf_gym.params` (parameters and presets), :mod:`~blf_gym.dynamics`,
:mod:`~blf_gym.uncertainty`, :mod:`~blf_gym.reference`, :mod:`~blf_gym.bounds`,
:mod:`~blf_gym.registry` (controllers and observers by name), :mod:`~blf_gym.simulate` (the compiled closed
loop), :mod:`~blf_gym.metrics`, :mod:`~blf_gym.scenarios`, :mod:`~blf_gym.env`,
:mod:`~blf_gym.vector`, :mod:`~blf_gym.sources` (the import closures that key every compiled cache), :mod:`~blf_gym.safety` (:class:`SafetyGymnasiumWrapper`, Safety-Gymnasium's
six-value ``step`` with the cost).
"""

from gymnasium.envs.registration import register, registry

from .params import PRESETS, Scenario, preset
from .safety import SafetyGymnasiumWrapper

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "PRESETS", "SafetyGymnasiumWrapper", "Scenario", "preset", "__version__"]

ENV_IDS = {"plain": "PlanarBLF-v0", "residual": "PlanarBLFResidual-v0"}
"""The registered env of each mode: in plain mode the action is the whole torque, in residual mode
a torque added to the law's."""

if ENV_IDS["plain"] not in registry:
    register(
        id=ENV_IDS["plain"],
        entry_point="blf_gym.env:make_env",
        vector_entry_point="blf_gym.vector:PlanarBLFVectorEnv",
    )
if ENV_IDS["residual"] not in registry:
    register(
        id=ENV_IDS["residual"],
        entry_point="blf_gym.env:make_residual_env",
        vector_entry_point="blf_gym.vector:make_residual_vector_env",
        kwargs={"controller": "proposed"},
    )

"""blf-gym: the uncertain 3-DOF planar arm of Tran et al. (Electronics 2020, 9, 1355) with
time-varying output constraints, as a closed-loop simulator and a Gymnasium environment.

Importing the package registers ``PlanarBLF-v0`` (plain: the action is the torque) and
``PlanarBLFResidual-v0`` (residual over the LESO + barrier-Lyapunov law), both with a native
vector entry point for ``gym.make_vec``.

Sub-packages, by role (docs/layout.md; imports point down this list, never up):

- :mod:`blf_gym.envs`: the envs, the observation, the scenarios and suites, the levels;
- :mod:`blf_gym.kernel`: the compiled closed loop (:class:`~blf_gym.kernel.simulate.ClosedLoop`), the reward;
- :mod:`blf_gym.plugins`: the block protocol and the registry of controllers, observers and policies;
- :mod:`blf_gym.model`: parameters and presets, dynamics, uncertainties, reference, bounds;
- :mod:`blf_gym.jit` and :mod:`blf_gym.results`: the compiled caches' keys and maths; the results
  schema and atomic output.
"""

from gymnasium.envs.registration import register, registry

from blf_gym.model.params import PRESETS, Scenario, preset
from blf_gym.envs.safety import SafetyGymnasiumWrapper

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "PRESETS", "SafetyGymnasiumWrapper", "Scenario", "preset", "__version__"]

ENV_IDS = {"plain": "PlanarBLF-v0", "residual": "PlanarBLFResidual-v0"}
"""The registered env of each mode: in plain mode the action is the whole torque, in residual mode
a torque added to the law's."""

if ENV_IDS["plain"] not in registry:
    register(
        id=ENV_IDS["plain"],
        entry_point="blf_gym.envs.env:make_env",
        vector_entry_point="blf_gym.envs.vector:PlanarBLFVectorEnv",
    )
if ENV_IDS["residual"] not in registry:
    register(
        id=ENV_IDS["residual"],
        entry_point="blf_gym.envs.env:make_residual_env",
        vector_entry_point="blf_gym.envs.vector:make_residual_vector_env",
        kwargs={"controller": "proposed"},
    )

"""agents: training, evaluation and sweeps of Stable-Baselines3 agents on PlanarBLF.

The only package allowed to import torch and stable-baselines3 (lazily: importing ``agents``
itself stays light). ``agents.load_agent`` is the one loader of a trained agent.
"""


def load_agent(path):
    """(SB3 model, metadata, VecNormalize statistics or None) of a trained agent (see
    :func:`agents.loading.load_agent`)."""
    from .loading import load_agent as _load

    return _load(path)


__all__ = ["load_agent"]

"""agents: training, evaluation and sweeps of Stable-Baselines3 agents on PlanarBLF.

The only package allowed to import torch and stable-baselines3 (lazily: importing ``agents``
itself stays light). ``agents.load_agent`` is the one loader of a trained agent.
"""


def load_agent(path):
    """(SB3 model, metadata, VecNormalize statistics or None) of a trained agent (see
    :func:`agents.loading.load_agent`)."""
    from .loading import load_agent as _load

    return _load(path)


def load_pretrained(name, scenario=None, reward="score", **env_kwargs):
    """(model, env) of a shipped agent, the env made with the kwargs it was trained with (see
    :func:`agents.loading.load_pretrained`)."""
    from .loading import load_pretrained as _load

    return _load(name, scenario, reward, **env_kwargs)


__all__ = ["load_agent", "load_pretrained"]

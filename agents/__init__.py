"""agents: residual set-up, training and evaluation of Stable-Baselines3 agents.

Stub for now: the training (``blf-train``) and evaluation (``blf-eval``) commands arrive with the
agents issue. It is the only package allowed to import torch and stable-baselines3.
"""

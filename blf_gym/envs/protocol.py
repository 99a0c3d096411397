"""The benchmark's protocol, declared once: which suites exist, which are held out, where each
suite's evaluation seeds start, how many episodes ``blf-eval`` scores, the groups a learning curve
reads, and the second yardstick. :mod:`blf_gym.envs.scenarios` (which draws the suites) and
``agents`` (blf-eval, blf-train's curves, blf-sweep, blf-falsify) read these names from here; none
of them defines a seed offset of its own.

Seeds, by range (each suite's episode ``k`` uses scenario seed ``offset + k``):

- below :data:`EVAL_SEED_OFFSET`: training (an agent's seed and its envs' seeds);
- :data:`EVAL_SEED_OFFSET` (10,000) on: the training suite's held-out evaluation episodes;
- :data:`STRESS_SEED_OFFSET` (20,000) on: the stress suite (held out);
- :data:`CERTIFICATE_SEED_OFFSET` (30,000) on: the certificate suite (held out).

``tests/test_protocol.py`` checks that the ranges never meet for the episode counts any command uses.
"""

from __future__ import annotations

from blf_gym.model.params import PRESETS

__all__ = ["SUITES", "HELD_OUT_SUITES", "EVAL_SEED_OFFSET", "STRESS_SEED_OFFSET", "CERTIFICATE_SEED_OFFSET",
           "SUITE_SEED_SPAN", "PROTOCOL_SEEDS", "CURVE_GROUPS", "REFERENCE", "suite_seed_offset"]

SUITES = ("randomized", "stress", "certificate")
"""The scenario suites: the training suite (``randomized``) and the two held-out ones."""

HELD_OUT_SUITES = ("stress", "certificate")
"""Suites no training, tuning, seed choice, early stopping or sweep objective may read."""

EVAL_SEED_OFFSET = 10_000
"""The training suite's held-out evaluation episodes use scenario seeds from here, above every
training seed."""

STRESS_SEED_OFFSET = 20_000
"""The stress suite's evaluation episodes use scenario seeds from here."""

CERTIFICATE_SEED_OFFSET = 30_000
"""The certificate suite's episodes use scenario seeds from here."""

SUITE_SEED_SPAN = 10_000
"""How many episodes a suite may score before its seeds would reach the next suite's."""

PROTOCOL_SEEDS = {"randomized": 20, "stress": 50}
"""The benchmark's protocol: the paper presets, 20 held-out episodes of the training suite and 50
of the stress suite (what ``blf-eval`` runs by default)."""

CURVE_GROUPS = (*PRESETS, "randomized")
"""The groups the learning curves and the sweeps score: each paper preset, and held-out episodes of
the training suite (never a held-out suite)."""

REFERENCE = "ppc"
"""The second yardstick of every record (``score_vs_reference``): the controller with the best
training-suite score on the protocol when it was fixed (2026-12-06, docs/control/protocol.md:
prescribed-performance control, 9.79, against the tuned law's 7.90 and full-state PD's 6.40), chosen
once and fixed for a release. It is run on the inner path on the same scenarios and noise seeds as
the baselines, and its own rows carry no score against itself."""


def suite_seed_offset(suite: str) -> int:
    """First scenario seed of a suite's evaluation episodes."""
    offsets = {"randomized": EVAL_SEED_OFFSET, "stress": STRESS_SEED_OFFSET, "certificate": CERTIFICATE_SEED_OFFSET}
    if suite not in offsets:
        raise ValueError(f"unknown suite {suite!r}; accepted values: {list(SUITES)}")
    return offsets[suite]

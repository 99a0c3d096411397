"""The certificate suite (blf_gym.envs.scenarios): held-out cases where the filters' assumptions are
expected to fail (early forces, corners and uniform draws of the documented safe ranges), drawn
from seeds of their own, and refused for training like the stress suite."""

from __future__ import annotations

import numpy as np
import pytest

from blf_gym.model.params import preset
from blf_gym.envs.scenarios import CERTIFICATE_SEED_OFFSET, SAFE_RANGES, STRESS_SEED_OFFSET, sample_suite


def _case(seed: int):
    return sample_suite(np.random.default_rng(seed), preset("paper-0.1hz"), "certificate")


def _knobs(sc) -> dict:
    return {"frequency": sc.reference.frequency, "force": sc.force.wrench[0], "force_onset": sc.force.onset,
            "payload": sc.arm.masses[-1], "angle_noise_std": sc.angle_noise_std}


def test_its_cases_are_the_three_kinds_in_their_ranges():
    base = preset("paper-0.1hz")
    kinds = {"early force": 0, "corner": 0, "uniform": 0}
    for seed in range(CERTIFICATE_SEED_OFFSET, CERTIFICATE_SEED_OFFSET + 200):
        sc = _case(seed)
        k = _knobs(sc)
        assert sc.name == "certificate"
        if k["force_onset"] <= 4.0 and 40.0 <= k["force"] <= 60.0 and k["payload"] == base.arm.masses[-1] \
                and sc.friction == base.friction:
            kinds["early force"] += 1
            assert 0.1 <= k["frequency"] <= 0.5 and sc.angle_noise_std == base.angle_noise_std
            continue
        ends = [k[name] in SAFE_RANGES[name] for name in ("frequency", "force", "force_onset", "payload",
                                                           "angle_noise_std")]
        if all(ends):
            kinds["corner"] += 1
            assert all(abs(e) == SAFE_RANGES["initial_error"][1] for e in sc.initial_error)
        else:
            kinds["uniform"] += 1
            assert not any(ends)  # a uniform draw lands on an end with probability 0
            for name, v in k.items():
                lo, hi = SAFE_RANGES[name]
                assert lo <= v <= hi, (name, v)
    # 0.4 / 0.3 / 0.3 of 200: each count within about 3 standard deviations
    assert 55 <= kinds["early force"] <= 105 and 35 <= kinds["corner"] <= 85 and 35 <= kinds["uniform"] <= 85, kinds


def test_its_draws_depend_on_the_seed_alone_and_differ_from_the_stress_suites():
    assert _case(CERTIFICATE_SEED_OFFSET + 7) == _case(CERTIFICATE_SEED_OFFSET + 7)
    assert _case(CERTIFICATE_SEED_OFFSET) != _case(CERTIFICATE_SEED_OFFSET + 1)
    assert CERTIFICATE_SEED_OFFSET >= STRESS_SEED_OFFSET + 10_000  # no overlap with the stress suite's seeds


def test_training_on_it_is_refused_as_held_out():
    from agents.config import RunSpec

    with pytest.raises(ValueError, match="certificate suite is held out"):
        RunSpec(algo="ppo", mode="residual", controller=None, observer="leso", scenario="certificate",
                timesteps=100, seeds=[0]).checked()

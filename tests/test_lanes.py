"""The batched kernel against the single-arm path, arm by arm and bit for bit.

A batch steps its arms in blocks of ``LANES`` lanes in lockstep; a single arm runs the same code
compiled for one lane. Every lane's own control flow (stopped, noisy, first-same-as-last, the
instability check, a terminating violation) must only decide what that lane keeps, so each arm of a
mixed batch must give exactly the numbers it gives alone: state, step counter, status, sums, the
last applied signals, the recorded samples and the instability counter, after every call. The batch
here mixes scenarios of the training suite, one arm that diverges (code 1), one whose instability
check fails (code 2), one that breaks a tight bound and ends (``terminate``), noise on every third
arm only, a residual that changes per call, and resets of some arms between calls; 13 arms leave
a partly filled last block (padding lanes).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from blf_gym.model.params import preset
from blf_gym.envs.scenarios import sample_suite
from blf_gym.kernel import simulate
from blf_gym.kernel.simulate import LANES, ClosedLoop

N = 13
CALLS = (40, 17, 40, 60)


def _scenarios(seeds):
    return [sample_suite(np.random.default_rng(s)) for s in seeds]


def _mixed():
    scs = _scenarios(range(N))
    scs[0] = preset("paper-0.1hz")
    scs[2] = dataclasses.replace(scs[2], sim=dataclasses.replace(scs[2].sim, divergence_limit=3.0))
    scs[5] = dataclasses.replace(scs[5], sim=dataclasses.replace(scs[5].sim, error_rtol=1e-9, error_atol=1e-12,
                                                                 unstable_steps=5))
    b = scs[7].bounds
    scs[7] = dataclasses.replace(scs[7], bounds=dataclasses.replace(b, upper_amplitude=0.1, lower_amplitude=0.1,
                                                                    upper_floor=1e-4, lower_floor=1e-4,
                                                                    decay_rate=2000.0))
    return scs


def _inputs():
    rng = np.random.default_rng(3)
    out = []
    for c, steps in enumerate(CALLS):
        res = rng.normal(size=(N, 3)) * (20.0 if c % 2 == 0 else 5.0)
        noise = np.zeros((N, steps, 3))
        noise[1::3] = rng.normal(size=noise[1::3].shape) * 1e-3
        out.append((steps, res, noise, c % 2 == 1, None if c < 2 else 0))
    return out


def _run(loop, arms, inputs, resets):
    """Outputs of every call for the listed arms (the loop holds exactly those arms)."""
    log = []
    for c, (steps, res, noise, terminate, rec_n) in enumerate(inputs):
        rec, nrec, status = loop.advance(steps, residual=res[arms], noise=noise[arms], terminate=terminate,
                                         record_samples=rec_n)
        log.append({"X": loop.X.copy(), "k": loop.ksteps.copy(), "rec": rec.copy(), "nrec": nrec.copy(),
                    "status": status.copy(), "sums": loop.sums.copy(), "last": loop.last.copy(),
                    "ur": loop.unstable_run.copy()})
        if c == 1:
            which = [i for i, a in enumerate(arms) if a in resets]
            if which:
                loop.set_scenarios([resets[arms[i]] for i in which], which=which)
    return log


def test_each_arm_of_a_mixed_batch_equals_the_arm_alone():
    assert N % LANES != 0  # the last block has padding lanes
    scs = _mixed()
    inputs = _inputs()
    resets = {a: sc for a, sc in zip(range(0, N, 4), _scenarios(range(100, 104)))}
    batch = ClosedLoop(scs, "proposed", threads=2, lanes=LANES)
    assert batch.lanes == LANES
    together = _run(batch, list(range(N)), inputs, resets)
    # the mixture this test is about actually happened
    first = together[0]["status"]
    assert first[2, 1] == 1 and first[5, 1] == 2
    assert together[1]["status"][7, 2] > 0 and together[1]["status"][7, 0] < CALLS[1]
    for a in range(N):
        single = ClosedLoop([scs[a]], "proposed", threads=1, lanes=1)
        assert single.lanes == 1
        alone = _run(single, [a], inputs, resets)
        for c, (t, s) in enumerate(zip(together, alone)):
            for key in t:
                np.testing.assert_array_equal(t[key][a : a + 1], s[key], err_msg=f"arm {a}, call {c}, {key}")


def test_lanes_is_checked():
    with pytest.raises(ValueError, match="lanes must be 1, 4 or None"):
        ClosedLoop([preset("paper-0.1hz")], "proposed", lanes=3)


def test_blocks_for_two_arms_or_more_and_a_single_arm_takes_a_compiled_build():
    sc = preset("paper-0.1hz")
    # both builds of this kernel are compiled by the test above (same worker or the disk cache)
    ClosedLoop([sc], "proposed", lanes=1)
    ClosedLoop([sc] * 2, "proposed", lanes=LANES)
    assert ClosedLoop([sc] * 2, "proposed", threads=2).lanes == LANES
    assert ClosedLoop([sc] * 9, "proposed").lanes == LANES
    assert ClosedLoop([sc], "proposed").lanes == 1
    assert ClosedLoop([sc] * 9, "proposed", lanes=1).lanes == 1
    # a single arm takes the batch build when only that one is compiled, rather than compiling
    conn = ClosedLoop([sc], "proposed", lanes=1).connection
    built = {1: True, LANES: True}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(simulate, "_is_cached", lambda k: built[1 if k is simulate._specialise(conn, 1) else LANES])
        assert simulate._choose_lanes(conn, 1) == 1 and simulate._choose_lanes(conn, 2) == LANES
        built.update({1: False, LANES: True})
        assert simulate._choose_lanes(conn, 1) == LANES
        built.update({1: True, LANES: False})
        assert simulate._choose_lanes(conn, 2) == LANES
        built.update({1: False, LANES: False})
        assert simulate._choose_lanes(conn, 1) == 1

"""blf-eval's memory does not grow with the number of episodes.

Before, every trajectory of every policy was kept to the end (the default protocol peaked at
11.5-12.4 GB). Now each episode is reduced to its EpisodeStats as it comes, and only a batch of
1 ms records is alive at once. Measured with tracemalloc (numpy reports its buffers to it), so the
test reads memory, not time."""

from __future__ import annotations

import tracemalloc

import numpy as np

from agents.evaluate import (AGENT_BATCH, CONTROLLER_BATCH, agent_episodes, build_scenarios, controller_episodes,
                             law_reference, main)
from blf_gym.results.metrics import episode_stats, summarize


def _peak(fn) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _suite(n, duration=0.5):
    return build_scenarios([], n, {}, duration, "randomized")[0][1]


def test_a_controller_s_peak_does_not_grow_with_its_episodes():
    small, large = _suite(2 * CONTROLLER_BATCH), _suite(8 * CONTROLLER_BATCH)
    run = lambda scs: summarize(controller_episodes("proposed", scs, threads=1), "p", "baseline", "s", 1e-4)  # noqa: E731
    run(small[:2])  # compile or load the kernel outside the measurement
    a, b = _peak(lambda: run(small)), _peak(lambda: run(large))
    # a record of these episodes is about 200 kB each: keeping all 128 would be 26 MB against 6.5 MB
    assert b < 1.3 * a, (a, b)


def test_an_agent_s_peak_does_not_grow_with_its_episodes_and_its_rows_do_not_change():
    meta = {"mode": "residual", "env_kwargs": {"controller": "proposed", "control_period": 0.01}}
    small, large = _suite(AGENT_BATCH, 0.2), _suite(3 * AGENT_BATCH, 0.2)
    law_reference(small[:2], meta, threads=1)
    a, b = _peak(lambda: law_reference(small, meta, threads=1)), _peak(lambda: law_reference(large, meta, threads=1))
    assert b < 1.3 * a, (a, b)
    # batches change nothing: the first AGENT_BATCH episodes of the long list score as they do alone
    from agents.episodes import _ZeroResidual

    alone = [episode_stats(t) for t in agent_episodes(_ZeroResidual(), meta, None, small, threads=1)]
    assert [s.rmse_deg for s in alone] == [s.rmse_deg for s in law_reference(large, meta, threads=1)[:AGENT_BATCH]]


def test_blf_eval_keeps_one_trace_per_group_for_the_plots(tmp_path, monkeypatch):
    # the plots draw each group's first episode: that is all blf-eval keeps of the signals
    import agents.eval_runner as ev  # where the run looks the plots up

    kept = {}
    real = ev.plots

    def spy(results, out):
        kept["n"] = [len(first) for _, first in results]
        kept["fields"] = sorted(vars(results[0][1][0]))
        return real(results, out)

    monkeypatch.setattr(ev, "plots", spy)
    assert main(["--controllers", "proposed", "bc", "--agents", "--scenarios", "--suite", "randomized",
                 "--suite-seeds", "5", "--duration", "0.2", "--no-progress", "--out", str(tmp_path)]) == 0
    assert kept["n"] == [1, 1]
    assert kept["fields"] == ["e1", "k_a", "k_b", "n_samples", "t", "u"]
    from agents.episodes import evaluate_controller

    assert np.isfinite(summarize([episode_stats(evaluate_controller("bc", _suite(1, 0.2))[0])], "x",
                                 "baseline", "s", 1e-4)["rmse_deg"]).all()

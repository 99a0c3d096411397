"""Test-run settings shared by tests/ and notebooks/ (collected by nbmake)."""

import os
from pathlib import Path

# The notebooks run in quick mode under pytest (short episodes, a few hundred training steps);
# opened by hand they run in full.
os.environ.setdefault("BLF_QUICK", "1")

# blf-eval in the test's own process unless a test asks for workers (tests patch its functions, and
# each run's two spawned workers would boot torch and numba again); tests/test_eval_parallel.py runs
# the workers with --jobs 2 and checks that they score the same records.
os.environ.setdefault("BLF_GYM_JOBS", "1")

# Every cache blf-gym keeps in its own folder (the plug-ins' compiled glue, blf-eval's law results,
# the NMPC's solver) goes to one temporary folder per test run, made here by the first process (the
# xdist controller, before it starts the workers) and inherited by the workers, their subprocesses
# and the notebooks' kernels through the environment; removed at the end of the run. The closed-loop
# kernels' builds live there too (blf_gym.kernel.simulate.kernel_folder), so every run of the suite
# compiles the kernels it needs once, shared by its workers and their subprocesses, as CI's fresh
# clone does.
if "BLF_GYM_TEST_CACHE" not in os.environ:
    import tempfile

    os.environ["BLF_GYM_TEST_CACHE"] = os.environ["BLF_GYM_CACHE_DIR"] = tempfile.mkdtemp(prefix="blf-gym-tests-")
    _OWN_CACHE = os.environ["BLF_GYM_TEST_CACHE"]
else:
    _OWN_CACHE = None

# Torch on one thread, as the README tells a user training beside the env: the env warns once per
# process when torch's threads and its own exceed the cores (tests that check that warning run in a
# fresh interpreter), and on the 2-core CI machine the suite's small trainings run faster so.
try:
    import torch
except ImportError:  # the agents' extra is not installed: nothing to set
    pass
else:
    torch.set_num_threads(1)


import pytest  # noqa: E402


def pytest_unconfigure(config):
    if _OWN_CACHE is not None and not hasattr(config, "workerinput"):
        import shutil

        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """List the closed-loop builds this run compiled (one line per build, from the run's own kernel
    cache): each costs about a minute of one core, most of the suite's time on a cold cache, so the
    list is where a shorter suite starts (fewer distinct laws, observers, filters, n and widths)."""
    if _OWN_CACHE is None or hasattr(config, "workerinput"):
        return
    builds = sorted({p.name.split(".")[0].rsplit("__", 1)[0]
                     for p in Path(_OWN_CACHE).glob("kernels/*/__pycache__/advance*.nbi")})
    if builds:
        terminalreporter.write_sep("-", f"{len(builds)} closed-loop builds compiled by this run")
        for b in builds:
            terminalreporter.write_line(b)


def pytest_report_header(config):
    """Say, before the first dot, that a first run compiles the closed-loop kernels first: without
    it the run prints nothing for minutes."""
    try:
        from blf_gym.kernel.simulate import kernels_cached
    except ImportError:
        return None
    if kernels_cached():
        return None
    return ("blf-gym: the closed-loop kernels are not compiled yet (first run of this checkout): the workers "
            "compile them before their first tests, several minutes on 2 cores; later runs load them")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a test of 20 s or more (a sweep, a training, a compile on "
                                       "purpose); run first, see pytest_collection_modifyitems")


def pytest_collection_modifyitems(config, items):
    """Slow tests first on every xdist worker, so that the workers end on short tests and neither
    waits long for the other at the end of a run.

    ``--dist worksteal`` hands worker k the k-th contiguous share of the collection (then moves
    tests from a busy worker's end to an idle one), so the slow tests are dealt out to the shares'
    fronts: whole modules, largest first, to the share with the fewest so far (one module's slow
    tests, such as the sweeps, never run on two workers at once). The same order on every worker,
    as xdist requires; without xdist, simply slow first."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    slow = [it for it in items if it.get_closest_marker("slow")]
    fast = [it for it in items if not it.get_closest_marker("slow")]
    if workers < 2:
        items[:] = slow + fast
        return
    modules: dict[str, list] = {}
    for it in slow:
        modules.setdefault(it.nodeid.split("::")[0], []).append(it)
    shares: list[list] = [[] for _ in range(workers)]
    for mod in sorted(modules, key=lambda m: -len(modules[m])):
        min(shares, key=len).extend(modules[mod])
    out, rest, left = [], fast, len(items)
    for k, share in enumerate(shares):
        size = left // (workers - k)  # what worksteal sends worker k first
        take = max(0, size - len(share))
        out += share + rest[:take]
        rest, left = rest[take:], left - size
    items[:] = out + rest


@pytest.fixture(autouse=True)
def _own_law_cache(tmp_path_factory, monkeypatch):
    """Each test starts with an empty cache of the law's episodes (agents/lawcache.py) of its own, so
    that blf-eval's reuse of one test's law runs never changes what another test sees."""
    try:
        import agents.lawcache as lawcache
    except ImportError:  # the agents' dependencies are not installed
        return
    folder = tmp_path_factory.mktemp("law")
    monkeypatch.setattr(lawcache, "_FOLDER", folder)  # blf-eval's worker processes take it too


# The closed-loop kernels most of the suite uses, compiled once at the start of a parallel run,
# split between the pytest-xdist workers (worker k builds every W-th). Each build takes about a
# minute here; without this the workers' first tests needed the same kernels at the same time, and
# one worker waited on the other's compile (the lock in blf_gym.kernel.simulate.ClosedLoop) instead of
# building another. Names a run does not have (an example plug-in not installed) are skipped.
_SUITE_KERNELS = [  # (controller, observer, residual filter, plain, lanes)
    # the batch build (4 lanes) of each, which batches of two arms or more use and single arms
    # take when theirs is not compiled; the one-lane build of the single envs' laws
    ("proposed", "leso", None, False, 4), ("none", "leso", None, False, 4), ("bc", "leso", None, False, 4),
    ("lesobc", "leso", None, False, 4), ("proposed", "leso", "barrier", False, 4),
    ("proposed_integral", "leso", None, False, 4), ("proposed", "eso4", None, False, 4),
    ("proposed", "leso", None, False, 1), ("proposed", "leso", "barrier", False, 1), ("none", "leso", None, False, 1),
]


@pytest.fixture(scope="session", autouse=True)
def _suite_kernels_split_between_workers():
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not worker.startswith("gw") or count < 2:
        return
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import ClosedLoop

    k = int(worker[2:])
    for controller, observer, filt, plain, lanes in _SUITE_KERNELS[k::count]:
        try:
            ClosedLoop([preset("paper-0.1hz")], controller, observer, threads=1, residual_filter=filt, plain=plain,
                       lanes=lanes)
        except (ValueError, LookupError):  # not installed here
            pass

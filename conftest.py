"""Test-run settings shared by tests/ and notebooks/ (collected by nbmake)."""

import os

# The notebooks run in quick mode under pytest (short episodes, a few hundred training steps);
# opened by hand they run in full.
os.environ.setdefault("BLF_QUICK", "1")

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


@pytest.fixture(autouse=True)
def _own_law_cache(tmp_path_factory, monkeypatch):
    """Each test starts with an empty cache of the law's episodes (agents/lawcache.py) of its own, so
    that blf-eval's reuse of one test's law runs never changes what another test sees."""
    try:
        import agents.lawcache as lawcache
    except ImportError:  # the agents' dependencies are not installed
        return
    folder = tmp_path_factory.mktemp("law")
    monkeypatch.setattr(lawcache, "_folder", lambda: folder)


# The closed-loop kernels most of the suite uses, compiled once at the start of a parallel run,
# split between the pytest-xdist workers (worker k builds every W-th). Each build takes about a
# minute here; without this the workers' first tests needed the same kernels at the same time, and
# one worker waited on the other's compile (the lock in blf_gym.simulate.ClosedLoop) instead of
# building another. Names a run does not have (an example plug-in not installed) are skipped.
_SUITE_KERNELS = [  # (controller, observer, residual filter, plain, lanes)
    ("proposed", "leso", None, False, 1), ("none", "leso", None, False, 1), ("bc", "leso", None, False, 1),
    ("lesobc", "leso", None, False, 1), ("proposed", "leso", "barrier", False, 1),
    ("proposed", "leso", "barrier", True, 1), ("proposed_integral", "leso", None, False, 1),
    ("proposed", "eso4", None, False, 1), ("proposed", "leso", None, False, 4),
]


@pytest.fixture(scope="session", autouse=True)
def _suite_kernels_split_between_workers():
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not worker.startswith("gw") or count < 2:
        return
    from blf_gym.params import preset
    from blf_gym.simulate import ClosedLoop

    k = int(worker[2:])
    for controller, observer, filt, plain, lanes in _SUITE_KERNELS[k::count]:
        try:
            ClosedLoop([preset("paper-0.1hz")], controller, observer, threads=1, residual_filter=filt, plain=plain,
                       lanes=lanes)
        except (ValueError, LookupError):  # not installed here
            pass

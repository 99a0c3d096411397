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

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

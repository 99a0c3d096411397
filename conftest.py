"""Test-run settings shared by tests/ and notebooks/ (collected by nbmake)."""

import os

# The notebooks run in quick mode under pytest (short episodes, a few hundred training steps);
# opened by hand they run in full.
os.environ.setdefault("BLF_QUICK", "1")

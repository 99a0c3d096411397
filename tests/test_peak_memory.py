"""benchmarks/peak_memory.py sums memory over a command's whole process tree: a parent that starts
two children, each holding 150 MB, peaks at more than the largest single process, which is all
``/usr/bin/time -v`` reports."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "peak_memory.py"

CHILD = "import time; x = bytearray(150_000_000); x[::4096] = b'1' * len(x[::4096]); time.sleep(1.5)"
PARENT = (f"import subprocess, sys; ps = [subprocess.Popen([sys.executable, '-c', {CHILD!r}]) for _ in range(2)]; "
          "[p.wait() for p in ps]")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_two_children_are_summed_and_the_exit_status_is_kept():
    p = subprocess.run([sys.executable, str(SCRIPT), "--interval", "0.1", "--", sys.executable, "-c", PARENT],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    m = re.search(r"peak summed RSS ([\d.]+) GB, summed PSS ([\d.]+) GB, largest process ([\d.]+) GB", p.stderr)
    assert m, p.stderr
    rss, pss, largest = map(float, m.groups())
    assert 0.15 <= largest < 0.25  # one child: its 150 MB and an interpreter
    assert rss >= 0.30 and pss >= 0.30  # both children at once, counted together
    q = subprocess.run([sys.executable, str(SCRIPT), "--", sys.executable, "-c", "raise SystemExit(3)"],
                       capture_output=True, text=True, timeout=60)
    assert q.returncode == 3

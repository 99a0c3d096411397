"""Compile time of the closed loop's builds, for one or two source trees, measured interleaved.

A build (one controller, observer, filter, n and block width) is compiled once per machine and then
loaded from numba's cache, so its compile time is paid by a first run, by every fresh CI machine,
and by the test suite (about thirty builds). Each measurement here runs in its own process with an
empty blf-gym cache folder (``BLF_GYM_CACHE_DIR``, a fresh temporary folder), builds the kernel and
advances it ten steps, and reports the process's CPU seconds for that (user + system, so that other
work on the machine does not count) and the wall time. With two trees the rounds alternate (A B A B)
and the medians and their ratio are printed, as in ``benchmarks/compare.py``.

    python benchmarks/compile_time.py TREE [TREE2] [--rounds 3] [--builds proposed:4 proposed:1 ...]

A build is ``CONTROLLER:LANES`` (LESO observer, the paper's 3 links). Numba's cache of the helpers
that are compiled on their own (not inlined; in the tree's ``__pycache__`` folders) is left as it
is, the same for both trees.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

_CHILD = r"""
import json, resource, sys, time
from blf_gym.kernel.simulate import ClosedLoop
from blf_gym.model.params import preset
ctrl, lanes = sys.argv[1], int(sys.argv[2])
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
ClosedLoop([preset("paper-0.1hz")] * lanes, ctrl, threads=1, lanes=lanes).advance(10)
r1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"cpu_s": r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime,
                  "wall_s": time.perf_counter() - t0}))
"""


def measure(tree: str, build: str) -> dict[str, float]:
    """One build's compile in a fresh process and an empty cache folder, from ``tree``."""
    ctrl, _, lanes = build.partition(":")
    with tempfile.TemporaryDirectory(prefix="blf_compile_") as cache:
        env = dict(os.environ, PYTHONPATH=tree, BLF_GYM_CACHE_DIR=cache)
        out = subprocess.run([sys.executable, "-c", _CHILD, ctrl, lanes or "1"], env=env, cwd=cache,
                             capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{tree}: the build {build} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trees", nargs="+", help="one or two source trees (their roots)")
    ap.add_argument("--rounds", type=int, default=3, help="measurements per tree and build (default 3)")
    ap.add_argument("--builds", nargs="+", default=["proposed:1", "proposed:4"],
                    help="CONTROLLER:LANES builds (default proposed:1 proposed:4)")
    args = ap.parse_args(argv)
    if len(args.trees) > 2:
        ap.error("at most two trees")
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    res: dict[tuple[str, str], list[dict[str, float]]] = {}
    for r in range(args.rounds):
        for build in args.builds:
            order = args.trees if r % 2 == 0 else args.trees[::-1]
            for tree in order:
                m = measure(tree, build)
                res.setdefault((tree, build), []).append(m)
                print(f"round {r + 1} {build:<16} {tree}: cpu {m['cpu_s']:.1f} s, wall {m['wall_s']:.1f} s", flush=True)
    print(f"\nmedians of {args.rounds} round(s), CPU seconds (wall in brackets):")
    for build in args.builds:
        row = []
        for tree in args.trees:
            ms = res[(tree, build)]
            row.append((statistics.median(m["cpu_s"] for m in ms), statistics.median(m["wall_s"] for m in ms)))
        text = "   ".join(f"{t}: {c:.1f} ({w:.1f})" for t, (c, w) in zip(args.trees, row))
        if len(row) == 2:
            text += f"   second/first {row[1][0] / row[0][0]:.3f}"
        print(f"  {build:<16} {text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

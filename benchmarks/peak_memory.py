"""Peak memory of a command and every process it starts, summed, sampled from /proc (Linux).

    python benchmarks/peak_memory.py [--interval 0.25] -- blf-eval --out runs/eval

``/usr/bin/time -v`` reports the largest single process's peak, which undercounts a run that
works in several processes (``blf-eval --jobs 2``). This samples the whole process tree every
``--interval`` seconds and prints, at the end, the wall time, the peak of the summed resident
memory (RSS), the peak of the summed proportional memory (PSS: pages shared between the
processes counted once, from ``/proc/PID/smaps_rollup``) and the largest single process's RSS.
A peak shorter than the interval can be missed; the exit status is the command's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time


def _children(pid: int) -> list[int]:
    out = []
    for task in os.listdir(f"/proc/{pid}/task") if os.path.isdir(f"/proc/{pid}/task") else []:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return out


def _tree(root: int) -> list[int]:
    seen, todo = [], [root]
    while todo:
        pid = todo.pop()
        seen.append(pid)
        todo += _children(pid)
    return seen


def _kb(pid: int, path: str, key: str) -> int:
    try:
        with open(f"/proc/{pid}/{path}") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--interval", type=float, default=0.25, help="seconds between samples (default 0.25)")
    p.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    args = p.parse_args(argv)
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd:
        p.error("give the command to measure after --")
    if args.interval <= 0:
        p.error(f"--interval must be > 0 s, got {args.interval}")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    rss = pss = largest = 0
    while proc.poll() is None:
        pids = _tree(proc.pid)
        sizes = [_kb(q, "status", "VmRSS:") for q in pids]
        rss = max(rss, sum(sizes))
        largest = max(largest, max(sizes, default=0))
        pss = max(pss, sum(_kb(q, "smaps_rollup", "Pss:") for q in pids))
        time.sleep(args.interval)
    wall = time.perf_counter() - t0
    print(f"peak_memory: wall {wall:.1f} s; peak summed RSS {rss / 1e6:.2f} GB, summed PSS {pss / 1e6:.2f} GB, "
          f"largest process {largest / 1e6:.2f} GB (sampled every {args.interval:g} s); exit {proc.returncode}",
          file=sys.stderr)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())

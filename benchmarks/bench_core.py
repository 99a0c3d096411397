"""Speed of the compiled closed loop and of ``blf-reproduce`` (issue: foundation, item 5).

Prints medians over repeated runs, measured in this run on this machine, beside the targets:

* target 1: one closed-loop step (plant + LESO + proposed law, ODE3, h = 0.1 ms) <= 0.8 us,
  amortised over a whole 30 s run (300,000 steps) inside one compiled call;
* target 2: ``blf-reproduce`` for all six cases <= 3 s of wall time, process start included,
  with a warm compilation cache.

Run:  python benchmarks/bench_core.py [--repeats 5] [--json docs/speed/core.json]
The first run also compiles (cached to disk); that time is reported separately, not in the medians.
``--json FILE`` adds this run's figures to FILE (``benchmarks/results_json.py``), from which
``python docs/tables.py`` writes the table of docs/speed.md.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _closed_loop_step_us(controller: str, repeats: int) -> tuple[float, list[float]]:
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import ClosedLoop

    sc = preset("paper-0.1hz")
    loop = ClosedLoop([sc], controller, threads=1)
    loop.advance(10)  # load or compile the kernel
    times = []
    for _ in range(repeats):
        loop.set_scenarios([sc])
        t0 = time.perf_counter()
        loop.advance(sc.sim.n_steps, record_samples=sc.sim.n_samples)
        times.append((time.perf_counter() - t0) / sc.sim.n_steps * 1e6)
    return statistics.median(times), times


def _reproduce_wall_s(repeats: int) -> tuple[float, list[float]]:
    exe = Path(sys.executable).with_name("blf-reproduce")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "baselines.reproduce"]
    cmd.append("--no-progress")
    subprocess.run(cmd, check=True, capture_output=True)  # warm the cache
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also add this run's figures to FILE (e.g. docs/speed/core.json)")
    args = ap.parse_args()
    import results_json

    start = results_json.context()

    t0 = time.perf_counter()
    import blf_gym.kernel.simulate  # noqa: F401

    import_s = time.perf_counter() - t0
    print(f"import blf_gym.kernel.simulate: {import_s:.2f} s")
    step_us, step_us_runs = {}, {}
    print("\nclosed-loop step, 30 s run in one compiled call (median of "
          f"{args.repeats}):")
    for ctrl in ("none", "bc", "lesobc", "proposed"):
        med, all_t = _closed_loop_step_us(ctrl, args.repeats)
        step_us[ctrl], step_us_runs[ctrl] = med, all_t
        extra = ""
        if ctrl == "proposed":
            extra = f"   target <= 0.80 us  ratio {med / 0.8:.2f}x"
        print(f"  {ctrl:<9} {med:6.3f} us/step  (runs: {', '.join(f'{v:.3f}' for v in all_t)}){extra}")

    med, all_t = _reproduce_wall_s(args.repeats)
    print(f"\nblf-reproduce, six cases, process start included (median of {args.repeats}): "
          f"{med:.2f} s   target <= 3.00 s  ratio {med / 3.0:.2f}x")
    print(f"  runs: {', '.join(f'{v:.2f}' for v in all_t)}")
    if args.json:
        results_json.add_run(args.json, "benchmarks/bench_core.py", {
            "repeats": args.repeats, "import_s": import_s, "step_us": step_us, "step_us_runs": step_us_runs,
            "reproduce_s": med, "reproduce_s_runs": all_t}, start)


if __name__ == "__main__":
    main()

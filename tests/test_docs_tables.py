"""Every generated table in the README and docs/ is what ``python docs/tables.py`` would write now:
the env's tables from the code's declarations, the results tables from the results files in docs/."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _module(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_generated_table_is_what_its_command_writes():
    tables = _module(ROOT / "docs" / "tables.py")
    made = tables.pages()
    assert ROOT / "docs" / "environment.md" in made and ROOT / "docs" / "control" / "protocol.md" in made
    stale = [str(p.relative_to(ROOT)) for p, text in made.items() if not p.exists() or p.read_text() != text]
    assert not stale, f"{stale} differ from what python docs/tables.py writes: run it"


def test_a_page_without_its_markers_is_refused():
    tables = _module(ROOT / "docs" / "tables.py")
    with pytest.raises(ValueError, match="no <!-- begin:x -->"):
        tables.fill("text without markers", "x", "| a |", "page.md")
    assert tables.fill("a\n<!-- begin:x -->\nold\n<!-- end:x -->\nb", "x", "new") == \
        "a\n<!-- begin:x -->\nnew\n<!-- end:x -->\nb"


def _start(commit: str = "abc1234") -> dict:
    return {"date": "2026-12-05T10:00:00+00:00", "commit": commit, "cpus": 2, "load_avg": [0.12, 0.3, 0.4],
            "python": "3.11.7", "command": "python benchmarks/x.py --json FILE"}


def test_a_benchmark_run_is_added_to_its_file_and_runs_of_another_commit_are_dropped(tmp_path):
    rj = _module(ROOT / "benchmarks" / "results_json.py")
    path = tmp_path / "speed" / "core.json"
    rj.add_run(path, "benchmarks/bench_core.py", {"x": 1}, _start("old0000"))
    rj.add_run(path, "benchmarks/bench_core.py", {"x": 2}, _start())
    rj.add_run(path, "benchmarks/bench_core.py", {"x": 3}, _start())
    doc = json.loads(path.read_text())
    assert doc["script"] == "benchmarks/bench_core.py" and [r["x"] for r in doc["runs"]] == [2, 3]
    assert doc["runs"][0]["commit"] == "abc1234"
    rj.write(tmp_path / "t.json", "benchmarks/bench_threads.py", {"rounds": 3}, _start())
    assert json.loads((tmp_path / "t.json").read_text())["rounds"] == 3
    assert not list(tmp_path.rglob(".*"))  # no temporary file left behind


def _speed_files(folder: Path) -> None:
    """Small hand-made benchmark files, in the shapes the scripts write (not measurements)."""
    rj = _module(ROOT / "benchmarks" / "results_json.py")
    for step, rep in ((0.64, 1.43), (0.70, 1.52)):
        rj.add_run(folder / "core.json", "benchmarks/bench_core.py", {
            "repeats": 5, "import_s": 0.5, "step_us": {"none": step - 0.04, "bc": step - 0.03, "lesobc": step - 0.02,
                                                       "proposed": step},
            "step_us_runs": {}, "reproduce_s": rep, "reproduce_s_runs": [rep]}, _start())
    for resid, r64 in ((90.2, 27_040.0), (94.6, 28_390.0)):
        rj.add_run(folder / "env.json", "benchmarks/bench_env.py", {
            "steps": 2000,
            "env_step_us": {"Pendulum-v1": 11.2, "PlanarBLF-v0": resid - 9, "PlanarBLFResidual-v0": resid},
            "fresh_process_residual_us": {"unfiltered": [93.0], "barrier": [101.0]},
            "vector": [{"num_envs": 64, "threads": 1, "steps_per_s": r64 / 1.8},
                       {"num_envs": 64, "threads": 2, "steps_per_s": r64}]}, _start())
    for gc, sps, worst in ((True, 1_563.0, 1.31), (True, 1_897.0, 27.0), (False, 1_700.0, 4.9)):
        rj.add_run(folder / "resets.json", "benchmarks/bench_resets.py", {
            "seconds": 15.0, "gc": gc, "residual_step_us": 100.0, "steps_per_s": sps, "steps": 26_000,
            "resets": 20_000, "reset_ms": {"median": 0.24, "p99": 0.5, "max": worst},
            "reset_cpu_ms": {"median": 0.2, "p99": 0.4, "max": 4.0}}, _start())
    rounds = {"base": [{"step_us": 0.82, "env_us": 125.6, "vec64": 23_000.0, "batch64_us": 0.74},
                       {"step_us": 0.83, "env_us": 128.1, "vec64": 24_000.0, "batch64_us": 0.75}],
              "new": [{"step_us": 0.85, "env_us": 127.5, "vec64": 38_042.0, "batch64_us": 0.425}]}
    medians = {t: {k: sorted(r[k] for r in rs)[len(rs) // 2] for k in rs[0]} for t, rs in rounds.items()}
    rj.write(folder / "compare.json", "benchmarks/compare.py", {
        "rounds": 2, "trees": {"base": {"path": "/tmp/base", "commit": "2c28fef"},
                               "new": {"path": "/work/main", "commit": "abc1234+dirty"}},
        "medians": medians, "runs": rounds}, _start())
    rj.write(folder / "threads.json", "benchmarks/bench_threads.py", {"rounds": 3, "num_envs": 8, "pairs": [
        {"env_threads": "default", "torch_threads": "default", "env_threads_used": 1, "torch_threads_used": 2,
         "steps_per_s": 2_504.4, "rounds_steps_per_s": [2_504.4]},
        {"env_threads": "2", "torch_threads": "1", "env_threads_used": 2, "torch_threads_used": 1,
         "steps_per_s": 10_981.0, "rounds_steps_per_s": [10_981.0]}]}, _start())


def test_the_benchmark_tables_are_written_from_their_files(tmp_path, monkeypatch):
    tables = _module(ROOT / "docs" / "tables.py")
    _speed_files(tmp_path / "speed")
    monkeypatch.setattr(tables, "DOCS", tmp_path)
    where = "on 2026-12-05 at commit abc1234, 2 CPUs, 1-minute load average 0.12 at the start"
    assert tables.speed_table().splitlines()[2:] == [
        "| one closed-loop step (plant + LESO + proposed law, 3 ODE3 stages), amortized over a 30 s run | "
        "0.64-0.70 us (BC 0.61-0.67, LESOBC 0.62-0.68, no law 0.60-0.66) | <= 0.8 us |",
        "| `blf-reproduce`, six cases, process start included, warm cache | 1.4-1.5 s | <= 3 s |",
        "| residual `env.step` through `gym.make` (100 integration steps) | 90-95 us (plain 81-86 us; "
        "Pendulum-v1: 11 us) | <= 100 us |",
        "| vector env, residual, N = 64 | 27,000-28,400 agent steps/s on 2 threads (15,000-15,800 on 1) | "
        ">= 15,000 |",
        "| plain `PlanarBLF-v0`, training suite, random actions, default reward (`benchmarks/bench_resets.py`; "
        "episodes end at a violation, so mostly resets) | 1,560-1,900 steps/s, episodes of 1.3 steps; a reset's "
        "median 0.24 ms (2.4 steps), p99 0.50 ms (5.0 steps), the worst of a run (20,000 resets) 1.31-27.00 ms "
        "(13.1-270.0 steps); with Python's garbage collector off (`--no-gc`), the worst 4.90 ms (49.0 steps), "
        "4.00 ms of the thread's own CPU time | >= 1,000 steps/s, no reset over 20 steps |",
        "",
        f"Ranges of the medians over separate runs: `bench_core.py` 2 runs, the last {where}; `bench_env.py` "
        f"2 runs, the last {where}; `bench_resets.py` 3 runs, the last {where}."]
    assert tables.compare_table().splitlines() == [
        "| what | base (2c28fef) | new (abc1234+dirty) | new / base | over rounds, base; new |",
        "|---|---|---|---|---|",
        "| closed-loop step (proposed + LESO), one arm, no noise | 0.830 us | 0.850 us | 1.02 | "
        "0.820-0.830; 0.850 us |",
        "| one step per arm, 64 mixed training-suite arms with noise, 1 thread | 0.750 us | 0.425 us | 0.57 | "
        "0.740-0.750; 0.425 us |",
        "| residual `env.step` | 128.1 us | 127.5 us | 1.00 | 125.6-128.1; 127.5 us |",
        "| vector env, residual, N = 64, 2 threads | 24,000 /s | 38,042 /s | 1.59 (speed) | "
        "23,000-24,000; 38,042 /s |",
        "", f"Medians of 2 interleaved rounds, {where}."]
    assert tables.threads_table().splitlines() == [
        "| env threads | torch threads | agent steps/s |", "|---|---|---|",
        "| 1 (the default) | 2 (torch's default) | 2,504 |", "| 2 | 1 | 10,981 |",
        "", f"8 arms, medians of 3 rounds, {where}."]


def test_a_benchmark_table_is_generated_exactly_when_its_files_exist():
    tables = _module(ROOT / "docs" / "tables.py")
    for page, name, files, _ in tables.MEASURED_BLOCKS:
        text = (ROOT / page).read_text()
        assert f"<!-- begin:{name} -->" in text and f"<!-- end:{name} -->" in text, (page, name)
        present = all((ROOT / "docs" / "speed" / f"{f}.json").is_file() for f in files)
        assert (name in tables.BLOCKS.get(page, {})) == present, (page, name)

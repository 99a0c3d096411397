"""blf-eval's output set on a bad day: a full disk, an interrupted run, a rerun into an old folder.

A full disk is simulated, not needed: ``blf_gym.results.io.atomic_path`` (through which every file of the
set is written) is wrapped so that one chosen file's write fails with ENOSPC, the way ``write()``
raises it: an OSError with no file name. The command must then name that file in one
``blf-eval: error:`` line with exit code 2, and leave the folder recognisably incomplete: no
``manifest.json``, or one saying ``"complete": false``.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import re
import os
import shutil
from pathlib import Path

import pytest

import blf_gym.results.io as bio
from agents.evaluate import _parser
from agents.evaluate import main as eval_main

# without the second yardstick (tests/test_second_yardstick.py): these tests count the law's runs
TINY = ["--controllers", "proposed", "--agents", "--scenarios", "paper-0.1hz", "--suite-seeds", "0",
        "--duration", "1", "--threads", "1", "--no-progress", "--reference", "none"]
ENOSPC = os.strerror(errno.ENOSPC)


def _err_lines(capsys) -> list[str]:
    # the numba compile notice may come first on a cold cache; it is not part of the error
    return [ln for ln in capsys.readouterr().err.splitlines()
            if ln.strip() and not ln.startswith("blf-gym: compiling")]


def _manifest(out: Path) -> dict | None:
    p = out / "manifest.json"
    return json.loads(p.read_text()) if p.exists() else None


def _complete(out: Path) -> bool:
    m = _manifest(out)
    return m is not None and m.get("complete") is True


def _leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.rglob(".*") if p.is_file())


def _wrap_atomic_path(monkeypatch, fail_name: str | None = None, when=lambda tmp: True,
                      log: list | None = None):
    """Wrap atomic_path: log each target's name (and, for the manifest, whether the one on disk
    says complete at that moment); raise ENOSPC, without a file name, after the block that writes
    ``fail_name`` (when ``when(tmp)``), as a write() or flush on a full disk would."""
    real = bio.atomic_path

    @contextlib.contextmanager
    def wrapped(path, suffix=""):
        path = Path(path)
        if log is not None:
            log.append((path.name, _complete(path.parent)))
        with real(path, suffix) as tmp:
            yield tmp
            if path.name == fail_name and when(tmp):
                raise OSError(errno.ENOSPC, ENOSPC)

    monkeypatch.setattr(bio, "atomic_path", wrapped)


def _says_complete(tmp: Path) -> bool:
    return json.loads(Path(tmp).read_text()).get("complete") is True


@pytest.fixture(scope="module")
def complete_set(tmp_path_factory) -> Path:
    """One finished tiny run (with trajectories) to copy from."""
    out = tmp_path_factory.mktemp("complete") / "out"
    assert eval_main([*TINY, "--save-traj", "--out", str(out)]) == 0
    return out


# ---------------------------------------------------------------------------------------------
# a full disk at each file of the set


@pytest.mark.parametrize("fail_name, when", [
    ("results.json", None),            # the first write of the run (after the first record)
    ("results.csv", None),
    ("error_paper-0.1hz.png", None),   # a plot
    ("manifest.json", None),           # the first manifest, written before anything else
    ("manifest.json", _says_complete),  # the last write: the complete manifest
], ids=["results.json", "results.csv", "plot", "manifest-first", "manifest-last"])
def test_a_full_disk_names_the_file_and_leaves_the_set_marked_incomplete(tmp_path, capsys, monkeypatch,
                                                                         fail_name, when):
    out = tmp_path / "out"
    _wrap_atomic_path(monkeypatch, fail_name, when or (lambda tmp: True))
    rc = eval_main([*TINY, "--out", str(out)])
    err = _err_lines(capsys)
    assert rc == 2, err
    assert len(err) == 1, err
    assert err[0].startswith("blf-eval: error: ")
    assert f"cannot write {out / fail_name}: {ENOSPC}" in err[0], err[0]  # the file, not the folder
    assert "Traceback" not in err[0]
    assert not _complete(out)  # no manifest, or one saying complete false
    assert _leftovers(out) == []  # no temporary files
    if fail_name != "manifest.json" or when is not None:
        # the run got past its first manifest: that one says complete false, and it is not verified
        assert _manifest(out)["complete"] is False
        assert "incomplete" in bio.verify_output_set(out)


def test_a_failed_write_in_atomic_path_names_the_target(tmp_path):
    target = tmp_path / "results.json"
    with pytest.raises(OSError) as info:
        with bio.atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise OSError(errno.ENOSPC, ENOSPC)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert bio.os_error_message(info.value, tmp_path).startswith(f"cannot write {target}: ")
    assert list(tmp_path.iterdir()) == []
    # a failure creating the temporary file names the target too, not the temporary name
    real_mkstemp = bio.tempfile.mkstemp

    def full(*a, prefix="", dir=None, **k):
        raise OSError(errno.ENOSPC, ENOSPC, os.path.join(dir, prefix + "x1y2z3.json"))

    bio.tempfile.mkstemp = full
    try:
        with pytest.raises(OSError) as info:
            with bio.atomic_path(target):
                pass
    finally:
        bio.tempfile.mkstemp = real_mkstemp
    assert info.value.filename == str(target)


# ---------------------------------------------------------------------------------------------
# a complete run, an interrupted run, a rerun


def test_a_complete_run_writes_the_manifest_last_listing_every_file(tmp_path, monkeypatch):
    out = tmp_path / "out"
    log: list = []
    _wrap_atomic_path(monkeypatch, log=log)
    assert eval_main([*TINY, "--save-traj", "--out", str(out)]) == 0
    names = [n for n, _ in log]
    assert names[0] == "manifest.json" and names[-1] == "manifest.json"
    assert names.count("manifest.json") == 2
    m = _manifest(out)
    assert m["complete"] is True and m["manifest_version"] == 1 and m["command"].startswith("blf-eval ")
    on_disk = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    listed = [e["path"] for e in m["files"]]
    assert sorted(listed) == [p for p in on_disk if p != "manifest.json"]
    assert {"results.json", "results.csv", "error_paper-0.1hz.png", "torque_paper-0.1hz.png",
            "traj/paper-0.1hz__proposed__0.npz"} == set(listed)
    for e in m["files"]:
        data = (out / e["path"]).read_bytes()
        assert e["bytes"] == len(data) and e["sha256"] == hashlib.sha256(data).hexdigest()
    assert bio.verify_output_set(out) is None
    # a changed file is caught
    with open(out / "results.csv", "a") as f:
        f.write("\n")
    assert "results.csv" in bio.verify_output_set(out)


def test_an_interrupted_run_keeps_its_finished_records_and_says_incomplete(tmp_path, capsys, monkeypatch):
    import agents.eval_runner as ev  # where the run looks the episodes up

    real = ev.controller_episodes
    calls = []

    def interrupt_second(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(ev, "controller_episodes", interrupt_second)
    out = tmp_path / "out"
    args = list(TINY)
    args.insert(args.index("paper-0.1hz") + 1, "paper-0.5hz")  # two records; stopped in the second
    # in this process, where the patch holds (test_eval_parallel.py interrupts the workers)
    assert eval_main([*args, "--out", str(out), "--jobs", "1"]) == 130
    recs = json.loads((out / "results.json").read_text())["records"]
    assert [r["scenario"] for r in recs] == ["paper-0.1hz"]  # the finished record is kept
    m = _manifest(out)
    assert m is not None and m["complete"] is False
    assert "incomplete" in capsys.readouterr().err


def test_a_rerun_into_a_complete_set_invalidates_its_manifest_before_writing(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    old = {"results.json": b'{"schema_version": 2, "provenance": {}, "records": []}\n', "results.csv": b"policy\n"}
    out.mkdir()
    for name, data in old.items():
        (out / name).write_bytes(data)
    (out / "manifest.json").write_text(json.dumps({
        "manifest_version": 1, "complete": True, "command": "blf-eval (an earlier run)",
        "files": [{"path": n, "bytes": len(d), "sha256": hashlib.sha256(d).hexdigest()} for n, d in old.items()]}))
    assert _complete(out)  # the old set is complete
    log: list = []
    _wrap_atomic_path(monkeypatch, "results.json", log=log)  # the new run stops at its first write
    assert eval_main([*TINY, "--out", str(out)]) == 2
    # the old complete manifest was gone before the first file of the new set was written
    # (the law's episodes kept in the cache folder, agents/lawcache.py, are not part of the set)
    first = next(i for i, (n, _) in enumerate(log) if n != "manifest.json" and not re.fullmatch(r"[0-9a-f]{64}\.json", n))
    assert log[first] == ("results.json", False)
    assert not _complete(out)
    assert "incomplete" in bio.verify_output_set(out)
    assert f"cannot write {out / 'results.json'}" in _err_lines(capsys)[0]


def test_report_warns_on_an_incomplete_or_changed_set(complete_set, tmp_path, capsys):
    from agents.report import main as report_main

    out = tmp_path / "out"
    shutil.copytree(complete_set, out)
    (out / "manifest.json").unlink(missing_ok=True)
    report = [str(out / "results.json"), "--json", str(tmp_path / "r.json")]

    def entry(name, data):
        return {"path": name, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}

    # no manifest (a set from before manifests, or from blf-reproduce): no warning
    assert report_main(report) == 0
    assert "warning" not in capsys.readouterr().err
    data = (out / "results.json").read_bytes()
    for complete, files, says in [(True, [entry("results.json", data)], None),
                                  (False, [], "incomplete"),
                                  (True, [entry("results.json", data + b" ")], "differs")]:
        (out / "manifest.json").write_text(json.dumps({"manifest_version": 1, "complete": complete,
                                                       "command": None, "files": files}))
        assert report_main(report) == 0
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning")]
        if says is None:
            assert err == []
        else:
            assert len(err) == 1 and says in err[0], err


def test_help_describes_the_manifest():
    text = _parser().format_help() + (_parser().description or "")
    import agents.evaluate as ev

    assert "manifest.json" in text and "complete" in text and "manifest.json" in ev.__doc__


def test_the_table_keeps_its_columns_aligned_for_long_names_and_large_errors(tmp_path, capsys):
    """A long agent name, a varied label and five-digit RMSEs (a plain agent that turned the arm
    over) widen their columns instead of pushing the others out of line; a diverged group says so
    in its own column, which the legend explains."""
    from agents.eval_tables import TABLE_NAME_MAX, table as _table

    out = tmp_path / "set"
    assert eval_main([*TINY, "--out", str(out), "--no-plots"]) == 0
    legend = " ".join(capsys.readouterr().out.split())
    assert "div: yes when an episode's simulation diverged" in legend
    rec = json.loads((out / "results.json").read_text())["records"][0]
    wild = dict(rec, policy="ppo_lagrangian_curriculum_seed_0_of_three", scenario="paper-0.1hz+frequency=0.5",
                rmse_deg=[2604.1, 11871.33, 0.5], diverged=True)
    lines = _table([rec, wild]).splitlines()
    bars = [[i for i, ch in enumerate(ln) if ch == "|"] for ln in (lines[0], *lines[2:])]
    assert len({tuple(b) for b in bars}) == 1, lines  # every row's separators at the header's places
    assert "11871.33" in lines[3] and lines[3].rstrip().endswith("yes") and lines[2].rstrip().endswith("-")
    name = lines[3].split()[0]
    assert len(name) == TABLE_NAME_MAX and name.startswith("ppo_lag") and name.endswith("three")


def test_the_plots_legend_covers_no_axes_and_overlapping_policies_differ():
    """The legend sits outside every axes (it used to cover joint 1's upper bound), and two
    policies with the same curve are drawn in different colours, styles and widths, so the one
    underneath still shows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from types import SimpleNamespace

    from agents.eval_tables import _figure

    t = np.linspace(0.0, 1.0, 101)
    e1 = np.radians(np.outer(np.sin(6 * t), [1.0, 0.5, 0.2]))
    bound = np.radians(np.full((101, 3), 2.0))
    tr = SimpleNamespace(t=t, e1=e1, k_a=bound, k_b=bound, u=np.outer(t, [1.0, 2.0, 3.0]), n_samples=101)
    rows = [({"policy": name, "kind": "baseline", "episodes": 1}, tr) for name in ("proposed", "ppc", "funnel")]
    fig = _figure("paper-0.1hz", rows, "error")
    fig.canvas.draw()
    legend = fig.legends[0].get_window_extent()
    for ax in fig.axes:
        assert not legend.overlaps(ax.get_window_extent()), ax.get_ylabel()
    lines = [ln for ln in fig.axes[0].get_lines() if ln.get_label() in ("proposed", "ppc", "funnel")]
    assert len({(ln.get_color(), str(ln.get_linestyle()), ln.get_linewidth()) for ln in lines}) == 3
    assert lines[0].get_linewidth() > lines[-1].get_linewidth()  # the first drawn is the widest
    plt.close(fig)

"""The benchmarks' ``--json FILE``: their figures saved for ``python docs/tables.py``.

Each file says when, where and from which commit its figures were measured (:func:`context`) and is
written through ``blf_gym.results.io``'s atomic writer, so an interrupted run leaves the old file or none.
Two kinds:

* :func:`write`: one measurement that is complete in itself (``compare.py``'s interleaved rounds,
  ``bench_threads.py``'s medians over rounds); the file is replaced.
* :func:`add_run`: one run of a script whose table shows the range over separate runs
  (``bench_core.py``, ``bench_env.py``, ``bench_resets.py``); the run is added to the file's
  ``runs``, and runs measured at another commit are dropped, so a file holds one commit's runs.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def commit(tree: Path = ROOT) -> str | None:
    """The short commit of the git tree ``tree``, with ``+dirty`` when tracked files outside ``docs/``
    differ from it (the results files written there do not count); None when ``tree`` is not in a
    git repository."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(tree), *args], check=True, capture_output=True,
                              text=True).stdout.strip()

    try:
        head = git("rev-parse", "--short=7", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)docs")
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


def context() -> dict[str, Any]:
    """When, where and how a measurement was taken: UTC time, commit, CPUs, the load average at
    the start (another busy process slows every figure), Python and the command line."""
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": commit(), "cpus": os.cpu_count(),
            "load_avg": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(), "command": " ".join(["python", *sys.argv])}


def _save(path: Path, doc: dict[str, Any]) -> None:
    from blf_gym.results.io import atomic_write_json

    atomic_write_json(path, doc)
    print(f"wrote {path}")


def write(path: str | os.PathLike, script: str, figures: dict[str, Any], start: dict[str, Any]) -> None:
    """Replace ``path`` with ``figures`` of ``script``, measured from ``start`` (:func:`context` taken
    before the measurement)."""
    _save(Path(path), {"script": script, **start, **figures})


def add_run(path: str | os.PathLike, script: str, figures: dict[str, Any], start: dict[str, Any]) -> None:
    """Add one run's ``figures`` (with ``start``, its :func:`context`) to the ``runs`` of ``path``,
    dropping the runs of another commit or of another script."""
    path = Path(path)
    runs: list[dict[str, Any]] = []
    if path.is_file():
        old = json.loads(path.read_text())
        if old.get("script") == script:
            runs = [r for r in old["runs"] if r.get("commit") == start["commit"]]
        if len(runs) < len(old.get("runs", [])):
            print(f"{path}: dropped {len(old.get('runs', [])) - len(runs)} run(s) of another commit or script")
    _save(path, {"script": script, "runs": [*runs, {**start, **figures}]})

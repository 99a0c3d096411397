"""docs/weights.py: trained weights kept in the history and restored by one command (issue 62, item 7).

Each test builds a small git repository with a copy of docs/weights.py and docs/budget/keep.sh, a
run folder committed in it, shelves the weights, and brings them back from a full, a shallow
(``--depth 1``) and a partial (``--filter=blob:none``) clone, checked byte for byte."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def git(repo: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t", "GIT_CONFIG_GLOBAL": os.devnull}
    out = subprocess.run(["git", "-c", "protocol.file.allow=always", *args], cwd=repo, capture_output=True,
                         text=True, env=env)
    assert out.returncode == 0, out.stderr
    return out.stdout


def weights(repo: Path, *args: str, ok: bool = True) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "docs/weights.py", *args], cwd=repo, capture_output=True, text=True)
    assert (out.returncode == 0) == ok, out.stderr
    return out


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    """A repository whose history holds a kept run: a checkpoint and the final model (random bytes,
    so a wrong blob cannot match), and a shipped agent."""
    r = tmp_path / "origin"
    (r / "docs" / "budget").mkdir(parents=True)
    shutil.copy(ROOT / "docs" / "weights.py", r / "docs" / "weights.py")
    shutil.copy(ROOT / "docs" / "budget" / "keep.sh", r / "docs" / "budget" / "keep.sh")
    run = r / "docs" / "budget" / "runs" / "x_s0"
    ck = run / "checkpoints" / "step_64"
    ck.mkdir(parents=True)
    rng = __import__("random").Random(0)
    for f in (ck / "model.zip", ck / "vecnormalize.pkl", run / "model.zip"):
        f.write_bytes(rng.randbytes(5000))
    (ck / "state.json").write_text(json.dumps({"files": ["model.zip", "vecnormalize.pkl"]}))
    (run / "metadata.json").write_text(json.dumps({"timesteps": 64}))
    (r / "agents" / "pretrained" / "a").mkdir(parents=True)
    (r / "agents" / "pretrained" / "a" / "model.zip").write_bytes(b"shipped")
    git(r, "init", "-q", "-b", "main")
    git(r, "add", ".")
    git(r, "commit", "-q", "-m", "a kept run")
    return r


def snapshot(repo: Path) -> dict[str, bytes]:
    return {p.relative_to(repo).as_posix(): p.read_bytes() for p in (repo / "docs" / "budget" / "runs").rglob("*")
            if p.is_file()}


def test_shelved_weights_leave_the_tree_and_come_back_from_every_kind_of_clone(repo, tmp_path):
    before = snapshot(repo)
    held = git(repo, "rev-parse", "HEAD").strip()
    out = weights(repo, "shelve", "docs/budget/runs")
    assert "shelved 3 file(s)" in out.stdout
    git(repo, "commit", "-q", "-m", "weights out of the tree")
    tracked = git(repo, "ls-files").split()
    assert not [p for p in tracked if p.startswith("docs/budget/runs") and p.endswith((".zip", ".pkl"))]
    assert "docs/budget/runs/x_s0/metadata.json" in tracked  # the records stay
    assert "agents/pretrained/a/model.zip" in tracked  # the shipped agent stays
    manifest = json.loads((repo / "docs" / "weights.json").read_text())["files"]
    assert {e["commit"] for e in manifest.values()} == {held}
    assert json.loads(weights(repo, "status").stdout) == {"shelved": 3, "present": 0, "missing": 3,
                                                          "shelved_mb": 0.0}
    for kind in ([], ["--depth", "1"], ["--filter=blob:none"]):
        clone = tmp_path / f"clone{len(list(tmp_path.iterdir()))}"
        git(tmp_path, "clone", "-q", "--no-local", *kind, f"file://{repo}", str(clone))
        if kind == ["--depth", "1"]:
            assert git(clone, "rev-list", "--count", "HEAD").strip() == "1"  # the old commit is not here
        assert not (clone / "docs/budget/runs/x_s0/model.zip").exists()
        weights(clone, "fetch", "--quiet")
        assert snapshot(clone) == before, kind
        assert git(clone, "status", "--porcelain") == ""  # restored files are excluded, not untracked
        assert "restored 0 file(s)" in weights(clone, "fetch").stdout  # a second fetch has nothing to do


def test_fetch_under_a_folder_restores_only_that_folder(repo):
    weights(repo, "shelve", "docs/budget/runs")
    git(repo, "commit", "-q", "-m", "out")
    weights(repo, "fetch", "docs/budget/runs/x_s0/checkpoints")
    assert (repo / "docs/budget/runs/x_s0/checkpoints/step_64/model.zip").is_file()
    assert not (repo / "docs/budget/runs/x_s0/model.zip").exists()


def test_a_blob_that_does_not_match_the_manifest_is_refused(repo):
    weights(repo, "shelve", "docs/budget/runs")
    git(repo, "commit", "-q", "-m", "out")
    path = repo / "docs" / "weights.json"
    m = json.loads(path.read_text())
    entry = m["files"]["docs/budget/runs/x_s0/model.zip"]
    entry["sha256"] = "0" * 64
    path.write_text(json.dumps(m))
    err = weights(repo, "fetch", ok=False).stderr
    assert "does not match" in err and "x_s0/model.zip" in err
    assert not (repo / "docs/budget/runs/x_s0/model.zip").exists()  # nothing half-written


def test_shelve_refuses_shipped_agents_uncommitted_files_and_empty_paths(repo):
    assert "shipped agent" in weights(repo, "shelve", "agents/pretrained", ok=False).stderr
    (repo / "docs/budget/runs/x_s0/model.zip").write_bytes(b"changed")
    assert "commit these first" in weights(repo, "shelve", "docs/budget/runs", ok=False).stderr
    assert "no committed weight files" in weights(repo, "shelve", "docs/budget/keep.sh", ok=False).stderr


def test_keep_restores_shelved_weights_and_forgets_the_ones_it_replaces(repo, tmp_path):
    """The long-run recipe through the shelf: the kept checkpoint is shelved, keep.sh --restore
    fetches it back into the run folder; a newer keep replaces it and drops its manifest entries."""
    before = snapshot(repo)
    weights(repo, "shelve", "docs/budget/runs")
    git(repo, "commit", "-q", "-m", "out")
    kept, run = "docs/budget/runs/x_s0", tmp_path / "job"
    p = subprocess.run(["bash", "docs/budget/keep.sh", "--restore", kept, str(run)], cwd=repo, capture_output=True,
                       text=True)
    assert p.returncode == 0, p.stderr
    assert (run / "checkpoints/step_64/model.zip").read_bytes() == before[f"{kept}/checkpoints/step_64/model.zip"]
    # the job goes on to step 128 and keeps it: step_64's entries and the old final model's go
    ck = run / "checkpoints" / "step_128"
    shutil.copytree(run / "checkpoints" / "step_64", ck)
    (ck / "model.zip").write_bytes(b"newer")
    (run / "model.zip").write_bytes(b"newer final")
    p = subprocess.run(["bash", "docs/budget/keep.sh", str(run), kept], cwd=repo, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    left = json.loads((repo / "docs" / "weights.json").read_text())["files"]
    assert list(left) == []  # the kept set is the new one, in the tree until it is committed and shelved


def test_the_repository_manifest_lists_only_files_out_of_the_tree():
    """docs/weights.json's files are not in the tree (a file both tracked and shelved would be restored
    over itself), each names a full commit and a SHA-256, and none is a shipped agent's."""
    path = ROOT / "docs" / "weights.json"
    if not path.is_file():
        pytest.skip("nothing shelved")
    files = json.loads(path.read_text())["files"]
    tracked = set(subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True).stdout.split())
    if not tracked:
        pytest.skip("not a git checkout")
    assert not tracked & set(files)
    for p, e in files.items():
        assert re.fullmatch(r"[0-9a-f]{40}", e["commit"]) and re.fullmatch(r"[0-9a-f]{64}", e["sha256"]), p
        assert not p.startswith("agents/pretrained/") and e["bytes"] > 0

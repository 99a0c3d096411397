"""Trained weights kept in the history, not in the working tree (issue 62, item 7).

A run folder in ``docs/`` keeps its records in the tree (``metadata.json``, ``curve.json``, the
reports and figures the pages read) and its weights (``model.zip``, ``vecnormalize.pkl``, a
checkpoint's files) in an earlier commit of main. ``docs/weights.json`` lists each shelved file:
its path, its size, its SHA-256 and the commit that holds it. One command brings them back:

    python docs/weights.py fetch                      # every shelved file not in the tree
    python docs/weights.py fetch docs/budget/runs/sbx_sac_s0   # only those under a folder
    python docs/weights.py status                     # shelved, present, missing, in MB
    python docs/weights.py shelve PATH...             # move committed weights under PATH out
    python docs/weights.py forget PATH...             # drop entries (a kept checkpoint replaced)

Why the history and not a separate artifacts repository: the weights are already in main's history
(every one was committed to be kept), so nothing needs uploading and nothing can go out of sync
with the commit that produced it; a clone with the whole history restores them offline, and a
shallow (``--depth 1``) or partial (``--filter=blob:none``) clone, which gets only the light tree,
fetches the one commit or the blobs it needs from the same remote on demand. The cost, a history
that still holds them, is paid once by a full clone; the working tree, which every checkout and
copy of the project pays for, is what shrinks.

``shelve`` records the commit that holds the files (``HEAD``; they must be committed there,
unchanged) and stages their removal; commit that. ``fetch`` reads each blob with ``git cat-file``;
where the clone lacks the commit (shallow), it first runs ``git fetch --depth 1 <remote> <commit>``.
Each file is written atomically and checked against its SHA-256, then listed in
``.git/info/exclude`` so that ``git status`` stays clean and it is not committed again by accident.
The shipped agents (``agents/pretrained``) are never shelved. No test or table needs the weights.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "docs" / "weights.json"
WEIGHT_SUFFIXES = (".zip", ".pkl", ".pt", ".pth", ".npz")
"""What counts as weights: the files SB3 and sbx write (model.zip, vecnormalize.pkl, replay buffers)."""
NEVER = ("agents/pretrained/",)
"""The shipped agents stay in the tree."""


class WeightsError(RuntimeError):
    """A shelve or fetch that cannot be done as asked; the message says what and how to proceed."""


def _git(*args: str, check: bool = True, binary: bool = False) -> subprocess.CompletedProcess:
    out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=not binary)
    if check and out.returncode != 0:
        err = out.stderr if not binary else out.stderr.decode(errors="replace")
        raise WeightsError(f"git {' '.join(args)} failed: {err.strip()}")
    return out


def load_manifest() -> dict[str, dict]:
    """path (relative to the root, '/'-separated) -> {"bytes", "sha256", "commit"}."""
    if not MANIFEST.is_file():
        return {}
    return json.loads(MANIFEST.read_text())["files"]


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def save_manifest(files: dict[str, dict]) -> None:
    _write_json(MANIFEST, {"about": "trained weights kept in main's history: python docs/weights.py fetch",
                           "files": dict(sorted(files.items()))})


def _rel(p: str | Path) -> str | None:
    """``p`` relative to the root ('/'-separated), None for a path outside the repository."""
    path = (Path.cwd() / p).resolve()
    try:
        return path.relative_to(ROOT).as_posix()
    except ValueError:
        return None


def _under(path: str, prefixes: list[str]) -> bool:
    return not prefixes or any(path == p or path.startswith(p.rstrip("/") + "/") for p in prefixes)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def shelve(paths: list[str]) -> list[str]:
    """Record the committed weight files under ``paths`` and stage their removal; the moved paths."""
    prefixes = [_rel(p) for p in paths]
    if not prefixes or None in prefixes:
        raise WeightsError(f"shelve: name folders or files inside {ROOT} whose weights leave the tree, got {paths}")
    tracked = _git("ls-files", "-z", "--", *prefixes).stdout.split("\0")
    chosen = [p for p in tracked if p and p.endswith(WEIGHT_SUFFIXES)]
    bad = [p for p in chosen if p.startswith(NEVER)]
    if bad:
        raise WeightsError(f"shelve: {bad[0]} is a shipped agent's file ({NEVER[0]} stays in the tree)")
    if not chosen:
        raise WeightsError(f"shelve: no committed weight files ({', '.join(WEIGHT_SUFFIXES)}) under {prefixes}")
    changed = _git("status", "--porcelain", "--", *chosen).stdout.strip()
    if changed:
        raise WeightsError(f"shelve: commit these first (the manifest names the commit that holds them):\n{changed}")
    head = _git("rev-parse", "HEAD").stdout.strip()
    files = load_manifest()
    for p in chosen:
        data = (ROOT / p).read_bytes()
        files[p] = {"bytes": len(data), "sha256": _sha256(data), "commit": head}
    save_manifest(files)
    for start in range(0, len(chosen), 200):
        _git("rm", "-q", "--", *chosen[start:start + 200])
    _git("add", "--", MANIFEST.relative_to(ROOT).as_posix())
    return chosen


def forget(paths: list[str]) -> list[str]:
    """Drop the manifest's entries under ``paths`` (a kept checkpoint replaced by a newer one)."""
    prefixes = [r for r in map(_rel, paths) if r is not None]
    files = load_manifest()
    if not prefixes:
        return []
    gone = [p for p in files if _under(p, prefixes)]
    for p in gone:
        del files[p]
    if gone:
        save_manifest(files)
    return gone


def _blob(path: str, commit: str) -> bytes:
    """The file's bytes at ``commit``, fetching the commit first where this clone lacks it."""
    spec = f"{commit}:{path}"
    out = _git("cat-file", "blob", spec, check=False, binary=True)
    if out.returncode == 0:
        return out.stdout
    remote = _git("remote", check=False).stdout.split()
    if not remote:
        raise WeightsError(f"{path}: commit {commit} is not in this clone and it has no remote to fetch it from")
    name = "origin" if "origin" in remote else remote[0]
    _git("fetch", "-q", "--no-tags", "--depth", "1", name, commit)
    return _git("cat-file", "blob", spec, binary=True).stdout


def _exclude(paths: list[str]) -> None:
    exclude = ROOT / _git("rev-parse", "--git-path", "info/exclude").stdout.strip()  # a worktree's is the common one
    have = set(exclude.read_text().splitlines()) if exclude.is_file() else set()
    new = [f"/{p}" for p in paths if f"/{p}" not in have]
    if new:
        exclude.parent.mkdir(parents=True, exist_ok=True)
        with exclude.open("a") as f:
            f.write("".join(line + "\n" for line in ["# restored by docs/weights.py fetch", *new]))


def fetch(paths: list[str], progress: bool = True) -> list[str]:
    """Write every shelved file under ``paths`` (all when empty) that is not in the tree; the
    written paths. A file present with other bytes is left alone and reported; a path with nothing
    shelved under it (a folder outside the repository included) restores nothing."""
    prefixes = [r for r in map(_rel, paths) if r is not None]
    files = load_manifest()
    if paths and not prefixes:
        return []
    todo = [p for p in files if _under(p, prefixes)]
    written = []
    for k, p in enumerate(todo, 1):
        entry, target = files[p], ROOT / p
        if target.is_file():
            if _sha256(target.read_bytes()) != entry["sha256"]:
                print(f"{p}: present with other bytes than the shelved file; left as it is", file=sys.stderr)
            continue
        data = _blob(p, entry["commit"])
        if _sha256(data) != entry["sha256"]:
            raise WeightsError(f"{p}: the blob at {entry['commit'][:12]} does not match docs/weights.json's SHA-256")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
        tmp.write_bytes(data)
        os.replace(tmp, target)
        written.append(p)
        if progress:
            print(f"[{k}/{len(todo)}] {p} ({len(data) / 1e6:.1f} MB)", file=sys.stderr)
    _exclude(written)
    return written


def status() -> dict[str, float]:
    files = load_manifest()
    present = [p for p in files if (ROOT / p).is_file()]
    return {"shelved": len(files), "present": len(present), "missing": len(files) - len(present),
            "shelved_mb": round(sum(e["bytes"] for e in files.values()) / 1e6, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="docs/weights.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name, text in (("fetch", "restore shelved weights (all, or those under PATHs)"),
                       ("shelve", "move committed weights under PATHs out of the tree"),
                       ("forget", "drop the manifest's entries under PATHs"), ("status", "counts and sizes")):
        p = sub.add_parser(name, help=text)
        if name != "status":
            p.add_argument("paths", nargs="*" if name == "fetch" else "+", metavar="PATH")
        if name == "fetch":
            p.add_argument("--quiet", action="store_true", help="no line per file")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "status":
            print(json.dumps(status()))
        elif args.cmd == "fetch":
            done = fetch(args.paths, progress=not args.quiet)
            print(f"restored {len(done)} file(s)")
        elif args.cmd == "shelve":
            done = shelve(args.paths)
            print(f"shelved {len(done)} file(s); commit the removal and docs/weights.json")
        else:
            print(f"forgot {len(forget(args.paths))} entr(ies)")
    except WeightsError as exc:
        print(f"docs/weights.py: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Atomic file output: a file is either absent or complete, never half-written.

Every command writes through these helpers (a temporary file in the same folder, then
``os.replace``), so an interrupted run leaves no truncated JSON, CSV, NPZ or PNG behind. An OSError
raised while writing (a full disk, say) names the file being written, not its temporary twin.

A command that writes a *set* of files (``blf-eval --out``) frames it with a manifest:
:func:`begin_output_set` first replaces any manifest in the folder with one saying
``"complete": false``, and :func:`finish_output_set`, after every file is written, replaces that
with ``"complete": true`` and each file's size and sha256. A set is complete only if its
``manifest.json`` says so and its files match (:func:`verify_output_set`).

The commands' other shared helpers live here too: one-line messages for an OSError
(:func:`os_error_message`), an output folder checked before a run (:func:`check_out_dir`), and a
docstring made plain text for ``--help`` (:func:`help_text`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

__all__ = ["cache_dir", "atomic_path", "atomic_write_text", "atomic_write_json", "atomic_write_npz", "check_out_dir",
           "os_error_message", "MANIFEST", "begin_output_set", "finish_output_set", "verify_output_set"]

MANIFEST = "manifest.json"
"""The name of an output set's manifest, in the set's folder."""
MANIFEST_VERSION = 1


def cache_dir() -> Path:
    """blf-gym's cache folder: ``BLF_GYM_CACHE_DIR`` if set, else ``blf-gym`` in the user's cache
    (``XDG_CACHE_HOME`` or ``~/.cache``). It holds the generated glue of the compiled closed loops
    (:mod:`blf_gym.plugins.blocks`), blf-eval's law results (``agents.lawcache``, ``law/``) and the NMPC's
    compiled solver (``baselines.mpc``, ``nmpc/``); deleting it is safe."""
    env = os.environ.get("BLF_GYM_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "blf-gym"


def _name_target(exc: OSError, path: Path) -> None:
    """Make ``exc`` name ``path`` when it names no file (a failed write() or flush) or a
    temporary file standing in for ``path`` (``.NAME.*`` beside it)."""
    try:
        named = None if exc.filename is None else Path(os.fsdecode(exc.filename))
    except TypeError:
        return
    if named is None or (named.parent == path.parent and named.name.startswith(f".{path.name}.")):
        exc.filename, exc.filename2 = str(path), None


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it into place only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
    except OSError as exc:
        _name_target(exc, path)
        raise
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates the file 0600; give it the permissions a plain open() would have
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:
        _name_target(exc, path)
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def atomic_write_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def os_error_message(exc: OSError, where: str | os.PathLike | None = None) -> str:
    """One line naming what failed and where, for an OSError a user can fix (disk full, read-only
    folder, a file where a folder is expected)."""
    import errno

    path = exc.filename or where
    reason = exc.strerror or str(exc)
    hint = {errno.ENOSPC: "free some space or choose another --out",
            errno.EDQUOT: "free some space or choose another --out",
            errno.EACCES: "choose a folder you can write to",
            errno.EPERM: "choose a folder you can write to",
            errno.EROFS: "the file system is read-only; choose another --out",
            errno.ENOTDIR: "a file stands where a folder is needed; choose another --out",
            errno.EEXIST: "a file stands where a folder is needed; choose another --out"}.get(exc.errno, "")
    return f"cannot write {path}: {reason}" + (f" ({hint})" if hint else "")


def check_out_dir(path: str | os.PathLike) -> Path:
    """Create the output folder ``path`` and check that it can be written to, before a long run.

    Raises OSError (with the path) if it is a file, cannot be created or is not writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(20, "it is a file, not a folder", str(path))
    path.mkdir(parents=True, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=".write-check.", dir=path)
    os.close(fd)
    os.unlink(probe)
    return path


def _digest(path: Path) -> tuple[int, str]:
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def begin_output_set(out_dir: str | os.PathLike, command: str | None = None) -> Path:
    """Before a set of files is written into ``out_dir``: remove any manifest there (a complete
    earlier set's included) and write one saying ``"complete": false``; return its path.

    Until :func:`finish_output_set` replaces it, the folder's files may be partial (say, a
    ``results.json`` holding only the records finished so far) or left from an earlier run."""
    path = Path(out_dir) / MANIFEST
    try:
        path.unlink()  # first, so that no complete-looking manifest outlives a failed write below
    except FileNotFoundError:
        pass
    atomic_write_json(path, {"manifest_version": MANIFEST_VERSION, "complete": False, "command": command,
                             "files": [], "note": "being written, or stopped before it was finished"})
    return path


def finish_output_set(out_dir: str | os.PathLike, files: Iterable[str | os.PathLike],
                      command: str | None = None) -> Path:
    """After every file of a set is written: replace the manifest in ``out_dir`` with one saying
    ``"complete": true`` and listing ``files`` (paths inside ``out_dir``, in the order given) with
    their size in bytes and sha256, as read back from disk; return its path."""
    out = Path(out_dir)
    entries = []
    for f in dict.fromkeys(Path(f) for f in files):
        size, sha = _digest(f)
        entries.append({"path": f.relative_to(out).as_posix(), "bytes": size, "sha256": sha})
    path = out / MANIFEST
    atomic_write_json(path, {"manifest_version": MANIFEST_VERSION, "complete": True, "command": command,
                             "files": entries})
    return path


def verify_output_set(out_dir: str | os.PathLike) -> str | None:
    """None if ``out_dir/manifest.json`` says the set is complete and every file it lists has its
    size and sha256; otherwise, in one line, why the set cannot be trusted as complete. Files in
    the folder that the manifest does not list are not part of the set and are not checked."""
    out = Path(out_dir)
    path = out / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        return f"no {MANIFEST} in {out}: the set was not finished, or was written without one"
    except (OSError, ValueError) as exc:
        return f"cannot read {path}: {exc}"
    if not isinstance(manifest, dict) or manifest.get("complete") is not True:
        return f"{path} says the set is incomplete (the run stopped or is still writing)"
    for entry in manifest.get("files") or []:
        f = out / entry["path"]
        try:
            size, sha = _digest(f)
        except OSError as exc:
            return f"{f} is listed in {path} but cannot be read ({exc.strerror or exc})"
        if (size, sha) != (entry.get("bytes"), entry.get("sha256")):
            return f"{f} differs from what {path} records (changed since the set was written)"
    return None


def help_text(doc: str | None) -> str:
    """A docstring as a command's ``--help`` shows it: reStructuredText's inline literals
    (````blf-train````) and roles (``:func:`x```, ``:data:`~a.b```) as plain text."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", doc or "")
    return re.sub(r"``([^`]+)``", r"\1", text)

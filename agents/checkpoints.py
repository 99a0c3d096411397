"""Training checkpoints that are either complete or absent.

SB3's ``CheckpointCallback`` writes a checkpoint as up to three loose files (model zip, replay
buffer, normalization statistics), one after the other. A process killed between two of them
leaves a model without its statistics, and a resume from it fails, or worse, silently trains
with fresh statistics. Here a checkpoint is a *set*: every file is written into a hidden folder
``checkpoints/.partial_<steps>_<pid>/`` with a ``state.json`` listing them, each file is flushed to
disk, and only then is the folder renamed to ``checkpoints/step_<steps>/``. A rename is atomic on
POSIX file systems, so a folder named ``step_<steps>`` is always complete.

:func:`find_checkpoints` lists the complete sets, newest first, and says what it skipped and why
(partial folders, sets with a missing or empty file, and loose SB3-style files of older runs
whose pair is missing). We write this by hand because no maintained library offers it: SB3's
callback, rl-zoo3 and Ray Tune's trainable checkpoints all write files one by one or expect to
own the training loop.
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import CheckpointCallback

__all__ = ["Checkpoint", "AtomicCheckpointCallback", "find_checkpoints", "save_checkpoint"]

MODEL, BUFFER, STATS, STATE = "model.zip", "replay_buffer.pkl", "vecnormalize.pkl", "state.json"


@dataclass
class Checkpoint:
    """One complete checkpoint: where its files are, and the state saved with it."""

    steps: int
    model: Path
    stats: Path | None = None
    buffer: Path | None = None
    state: dict[str, Any] = field(default_factory=dict)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_checkpoint(model: Any, ckpt_dir: Path, state: dict[str, Any], save_buffer: bool = True) -> Path:
    """Write model, replay buffer (if any) and normalization (if any) as one atomic set.

    ``state`` (JSON) is stored beside them, with the step count and the file list added. Returns
    the set's folder. A set that already exists for this step count is left as it is.
    """
    steps = int(model.num_timesteps)
    ckpt_dir = Path(ckpt_dir)
    final = ckpt_dir / f"step_{steps}"
    if final.is_dir():
        return final
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    tmp = ckpt_dir / f".partial_{steps}_{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        files = [MODEL]
        model.save(tmp / MODEL)
        if save_buffer and getattr(model, "replay_buffer", None) is not None:
            model.save_replay_buffer(tmp / BUFFER)
            files.append(BUFFER)
        norm = model.get_vec_normalize_env()
        if norm is not None:
            norm.save(str(tmp / STATS))
            files.append(STATS)
        (tmp / STATE).write_text(json.dumps({**state, "timesteps": steps, "files": files}, indent=2) + "\n")
        for f in [*files, STATE]:
            _fsync_file(tmp / f)
        _fsync_dir(tmp)
        os.rename(tmp, final)
        _fsync_dir(ckpt_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def _set_checkpoint(folder: Path) -> tuple[Checkpoint | None, str]:
    try:
        steps = int(folder.name.split("_", 1)[1])
    except (IndexError, ValueError):
        return None, "not a checkpoint folder name"
    try:
        state = json.loads((folder / STATE).read_text())
        files = list(state["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return None, f"its {STATE} is missing or unreadable"
    for f in files:
        p = folder / f
        if not p.is_file() or p.stat().st_size == 0:
            return None, f"{f} is missing or empty"
    if not zipfile.is_zipfile(folder / MODEL):
        return None, f"{MODEL} is not a complete zip"
    return Checkpoint(steps, folder / MODEL, folder / STATS if STATS in files else None,
                      folder / BUFFER if BUFFER in files else None, state), ""


def _legacy_checkpoints(ckpt_dir: Path, normalize: bool) -> tuple[list[Checkpoint], list[str]]:
    """SB3-style loose files (``model_<N>_steps.zip`` + ``model_vecnormalize_<N>_steps.pkl``)."""
    found, skipped = [], []
    for f in ckpt_dir.glob("model_*_steps.zip"):
        try:
            steps = int(f.stem.split("_")[1])
        except (IndexError, ValueError):
            continue
        stats = ckpt_dir / f"model_vecnormalize_{steps}_steps.pkl"
        buf = ckpt_dir / f"model_replay_buffer_{steps}_steps.pkl"
        if not zipfile.is_zipfile(f):
            skipped.append(f"{f.name} (not a complete zip)")
        elif normalize and not (stats.is_file() and stats.stat().st_size > 0):
            skipped.append(f"{f.name} (its normalization file {stats.name} is missing)")
        else:
            found.append(Checkpoint(steps, f, stats if normalize else None, buf if buf.is_file() else None))
    return found, skipped


def find_checkpoints(ckpt_dir: Path, normalize: bool) -> tuple[list[Checkpoint], list[str]]:
    """Complete checkpoints in ``ckpt_dir``, newest first, and a line per skipped one.

    ``normalize``: the run normalizes observations, so a set without statistics is incomplete.
    """
    ckpt_dir = Path(ckpt_dir)
    if not ckpt_dir.is_dir():
        return [], []
    found, skipped = [], []
    for folder in ckpt_dir.iterdir():
        if folder.name.startswith(".partial_"):
            skipped.append(f"{folder.name} (a checkpoint whose writing was interrupted)")
        elif folder.is_dir() and folder.name.startswith("step_"):
            ck, why = _set_checkpoint(folder)
            if ck is None:
                skipped.append(f"{folder.name} ({why})")
            elif normalize and ck.stats is None:
                skipped.append(f"{folder.name} (no normalization statistics in a normalized run)")
            else:
                found.append(ck)
    legacy, legacy_skipped = _legacy_checkpoints(ckpt_dir, normalize)
    have = {c.steps for c in found}
    found += [c for c in legacy if c.steps not in have]
    skipped += legacy_skipped
    found.sort(key=lambda c: c.steps, reverse=True)
    return found, sorted(skipped)


class AtomicCheckpointCallback(CheckpointCallback):
    """SB3's checkpoint callback, writing each checkpoint as one atomic set (:func:`save_checkpoint`).

    ``state()`` supplies the JSON saved with each set (the run's wall time so far, for example);
    ``on_saved(folder)`` is called after each one.
    """

    def __init__(self, save_freq: int, save_path: str, state=None, on_saved=None, **kwargs: Any) -> None:
        super().__init__(save_freq, save_path, **kwargs)
        self._state = state or dict
        self._on_saved = on_saved

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            folder = save_checkpoint(self.model, Path(self.save_path), self._state(), self.save_replay_buffer)
            if self._on_saved is not None:
                self._on_saved(folder)
        return True

"""Atomic checkpoint folders: write `.tmp-step-N/`, rename it to `step-N/`, then move the `last` pointer.

`last` is a relative symlink to the newest `step-N/` (so Hugging Face loaders open it like any model folder),
moved by creating the new link beside it and renaming it over the old one. With `checkpoint.keep_best`, `best` is
a link of the same kind to the checkpoint of the best validation pass so far, kept whatever `keep_last` says. Runs written before kept a one-line
pointer file; it is still read (model/persistence/checkpoint_path.py) and replaced by a symlink at the next commit.

Weights are given the mode of the other files (the umask's) before the commit: safetensors writes them 0600.

The file system side only; what goes inside a checkpoint is written by `training/export.py` (the Hugging Face
folder) and `training/state.py` (the accelerate training state).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from pathlib import Path

from openfly_agent.constants import BEST_POINTER_NAME, CHECKPOINTS_DIR, LAST_POINTER_NAME
from openfly_agent.model.persistence.checkpoint_path import last_pointer_target
from openfly_agent.utils.file_modes import follow_umask

logger = logging.getLogger(__name__)

STAGING_PREFIX = ".tmp-"
_STEP_DIR = re.compile(r"^step-(\d+)$")


def checkpoint_name(step: int) -> str:
    """Folder name of the checkpoint taken after `step` optimizer steps."""
    return f"step-{step:06d}"


class CheckpointManager:
    """Creates, commits, lists and prunes checkpoint folders under `<output_dir>/checkpoints/`.

    A checkpoint is complete once its staging folder has been renamed (the rename is the commit), so a crash
    at any moment leaves either the previous set of checkpoints or the new one, never half a `step-N/`.
    All methods touch the file system and must run on the main process only.

    Args:
        output_dir: the run's output folder.
        keep_last: how many complete checkpoints to keep (older ones are deleted after each commit).
    """

    def __init__(self, output_dir: str | Path, keep_last: int) -> None:
        if keep_last < 1:
            raise ValueError(f"keep_last must be >= 1, got {keep_last}")
        self.root = Path(output_dir) / CHECKPOINTS_DIR
        self.keep_last = keep_last

    def staging_dir(self, step: int) -> Path:
        """Where the checkpoint of `step` is written before it is committed."""
        return self.root / f"{STAGING_PREFIX}{checkpoint_name(step)}"

    def final_dir(self, step: int) -> Path:
        """Where the checkpoint of `step` lives once committed."""
        return self.root / checkpoint_name(step)

    def begin(self, step: int) -> Path:
        """Create an empty staging folder for `step` (removing a stale one left by a crash) and return it."""
        staging = self.staging_dir(step)
        if staging.exists():
            shutil.rmtree(staging)
        staging.mkdir(parents=True)
        return staging

    def commit(self, step: int) -> Path:
        """Rename the staging folder of `step` into place, point `last` at it and prune old checkpoints."""
        staging, final = self.staging_dir(step), self.final_dir(step)
        follow_umask(staging)
        _fsync_tree(staging)
        if final.exists():  # the same step saved again (e.g. the final save right after a periodic one)
            trash = self.root / f"{STAGING_PREFIX}old-{checkpoint_name(step)}"
            os.replace(final, trash)
            os.replace(staging, final)
            shutil.rmtree(trash)
        else:
            os.replace(staging, final)
        self._write_pointer(final.name)
        self.prune()
        logger.info("checkpoint committed: %s", final)
        return final

    def complete_checkpoints(self) -> list[Path]:
        """Committed checkpoint folders, oldest first."""
        if not self.root.is_dir():
            return []
        found = [
            (int(m.group(1)), p) for p in self.root.iterdir() if p.is_dir() and (m := _STEP_DIR.match(p.name))
        ]
        return [p for _, p in sorted(found)]

    def latest(self) -> Path | None:
        """The newest complete checkpoint: the one `last` names, else the highest step (None if none)."""
        pointer = self.root / LAST_POINTER_NAME
        candidate = last_pointer_target(pointer)
        if candidate is not None:
            if _STEP_DIR.match(candidate.name) and candidate.is_dir():
                return candidate
            logger.warning(
                "%s names %s, which is not a checkpoint folder; using the newest one", pointer, candidate
            )
        complete = self.complete_checkpoints()
        return complete[-1] if complete else None

    def best(self) -> Path | None:
        """The checkpoint `best` names (`checkpoint.keep_best`); None when there is no such link or folder."""
        pointer = self.root / BEST_POINTER_NAME
        if not pointer.is_symlink():
            return None
        target = self.root / os.readlink(pointer)
        return target if _STEP_DIR.match(target.name) and target.is_dir() else None

    def mark_best(self, step: int) -> None:
        """Point `best` at the committed checkpoint of `step` (one rename), then prune what it kept."""
        self._write_pointer(self.final_dir(step).name, BEST_POINTER_NAME)
        logger.info("best checkpoint so far: %s", self.final_dir(step))
        self.prune()

    def prune(self) -> list[Path]:
        """Delete all but the newest `keep_last` checkpoints (never those `last` and `best` name); return them."""
        complete = self.complete_checkpoints()
        protected = {self.latest(), self.best()}
        removed = [p for p in complete[: max(len(complete) - self.keep_last, 0)] if p not in protected]
        for path in removed:
            shutil.rmtree(path)
            logger.info("removed old checkpoint %s (keep_last=%d)", path, self.keep_last)
        return removed

    def remove_stale_staging(self) -> list[Path]:
        """Delete staging folders left by a crash mid-write (call at start-up, before any new save)."""
        if not self.root.is_dir():
            return []
        stale = [p for p in self.root.iterdir() if p.name.startswith(STAGING_PREFIX)]
        for path in stale:
            logger.warning("removing the incomplete checkpoint %s left by an interrupted save", path)
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        return stale

    def _write_pointer(self, name: str, pointer_name: str = LAST_POINTER_NAME) -> None:
        """Point `last` (or `pointer_name`) at the checkpoint folder `name` (a relative symlink, swapped in by one
        rename)."""
        pointer = self.root / pointer_name
        tmp = self.root / f"{STAGING_PREFIX}{pointer_name}"
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        os.symlink(name, tmp, target_is_directory=True)
        if pointer.is_dir() and not pointer.is_symlink():  # a copy that followed the link (shutil.copytree)
            logger.warning("replacing %s, a copied folder, by a link to %s", pointer, name)
            shutil.rmtree(pointer)
        os.replace(tmp, pointer)
        _fsync_dir(self.root)


def _fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (a rename or a new link in it) to disk."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(folder: Path) -> None:
    """Flush every file under `folder` to disk so the rename never commits data still in the page cache."""
    for path in folder.rglob("*"):
        if path.is_file():
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

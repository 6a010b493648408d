"""File-system helpers: atomic file writes (`write_atomic`) and the clean-up of the empty folders a failed command
created."""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable
from pathlib import Path


def write_atomic(path: str | Path, write: Callable[[Path], object]) -> None:
    """Have `write` fill a temporary file beside `path`, then rename it onto `path`: a reader sees the old file
    or the new one, never half of one, and a crash leaves the old file.

    The temporary name is private to this call (`.<name>.<pid>-<token>.tmp`), so two processes writing the same
    file at once (two runs finalizing one shared dataset) each rename their own complete file into place and the
    last rename wins. The temporary file is removed when `write` fails.

        write_atomic(path, lambda tmp: tmp.write_text(text))
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write `text` (UTF-8) to `path` through `write_atomic`."""
    write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def remove_empty_dirs(root: str | Path, children: tuple[str, ...]) -> None:
    """Delete the folders `root/<child>` that hold no file (with their empty subfolders), then `root` if it
    is empty now; a folder that holds a file stays, and nothing else under `root` is touched.

    What a command that fails before writing anything calls on its output folder, so no empty run folder is
    left behind. Another process removing or filling a folder at the same time is not an error.
    """
    root = Path(root)
    for child in children:
        remove_empty_tree(root / child)
    with contextlib.suppress(OSError):
        root.rmdir()


def remove_empty_tree(folder: str | Path) -> None:
    """Delete the folders under `folder` (and `folder` itself) that hold no file, deepest first."""
    if not Path(folder).is_dir():
        return
    walk = sorted(os.walk(folder), key=lambda entry: -len(Path(entry[0]).parts))  # deepest first
    for path, _, _ in walk:
        with contextlib.suppress(OSError):  # only an empty folder goes
            Path(path).rmdir()


def first_missing_dir(path: str | Path) -> Path | None:
    """The topmost folder of `path` (`path` or one of its parents) that does not exist yet, the first one that
    creating `path` creates; None when `path` exists.

        first_missing_dir("outputs/train/tiny")   # Path("outputs") in a fresh working directory
    """
    path = Path(path)
    return next((folder for folder in reversed((path, *path.parents)) if not folder.exists()), None)


def remove_created_dirs(path: str | Path, created: str | Path | None) -> None:
    """Delete `path` and its parents up to `created` (the folder `first_missing_dir` gave before they were made)
    while they are empty: a command that fails leaves none of the empty folders it created. A folder that holds
    anything stays, and so do its parents."""
    if created is None:
        return
    path, created = Path(path), Path(created)
    if created != path and created not in path.parents:
        return
    for folder in (path, *path.parents):
        try:
            folder.rmdir()
        except FileNotFoundError:
            pass
        except OSError:  # it holds something
            return
        if folder == created:
            return

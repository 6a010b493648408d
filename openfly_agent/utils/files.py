"""File-system helpers of the entry points."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


def remove_empty_dirs(root: str | Path, children: tuple[str, ...]) -> None:
    """Delete the folders `root/<child>` that hold no file (with their empty subfolders), then `root` if it
    is empty now; a folder that holds a file stays, and nothing else under `root` is touched.

    What a command that fails before writing anything calls on its output folder, so no empty run folder is
    left behind. Another process removing or filling a folder at the same time is not an error.
    """
    root = Path(root)
    for child in children:
        if not (root / child).is_dir():
            continue
        walk = sorted(os.walk(root / child), key=lambda entry: -len(Path(entry[0]).parts))  # deepest first
        for folder, _, _ in walk:
            with contextlib.suppress(OSError):  # only an empty folder goes
                Path(folder).rmdir()
    with contextlib.suppress(OSError):
        root.rmdir()

"""File permissions of written weights: the mode the process umask gives any plain file.

safetensors (0.8) writes its files through a private temporary file and a rename, so every `*.safetensors`
file it writes is 0600 whatever the umask, while every other file of a folder is created 0666 & ~umask (0644
under the usual 022): a group sharing a cluster file system could read the config but not the weights.
`follow_umask` gives the weights of a finished folder the mode of the files beside them.
"""

from __future__ import annotations

import os
from pathlib import Path

WEIGHTS_GLOB = "*.safetensors"
PLAIN_FILE_MODE = 0o666  # what open() asks for; the umask takes bits away


def current_umask() -> int:
    """The process umask, read without changing it where Linux exposes it (/proc/self/status `Umask:`)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)  # no /proc: read by setting and restoring it
    os.umask(mask)
    return mask


def plain_file_mode() -> int:
    """The permission bits a plain file created now gets (0o644 under umask 022)."""
    return PLAIN_FILE_MODE & ~current_umask()


def follow_umask(folder: str | Path) -> list[Path]:
    """Give every `*.safetensors` file under `folder` (recursively) the plain-file mode; return them."""
    mode = plain_file_mode()
    files = sorted(p for p in Path(folder).rglob(WEIGHTS_GLOB) if p.is_file() and not p.is_symlink())
    for path in files:
        if path.stat().st_mode & 0o777 != mode:
            os.chmod(path, mode)
    return files

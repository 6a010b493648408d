"""Small file helpers shared by the release builders: fresh output folders, linked copies, JSON I/O."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

DEFAULT_RELEASE_ROOT = Path("outputs") / "releases"  # release folders go to <this>/<repo name> by default


def prepare_output_dir(path: str | Path, overwrite: bool) -> Path:
    """Return an empty folder at `path`; refuse to touch a non-empty one unless `overwrite`."""
    path = Path(path)
    if path.exists() and any(path.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"release folder {path} is not empty: pass --overwrite=true or choose --output_dir"
            )
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    return path


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link `src` to `dst` (same file system, no extra space) or copy it."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def read_json(path: Path) -> Any:
    """Parse a JSON file; the error names the file."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read JSON ({err})") from err

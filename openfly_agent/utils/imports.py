"""Lazy imports of optional dependencies with an error that names the extra to install."""

from __future__ import annotations

import importlib
from types import ModuleType


def require_package(name: str, extra: str, module: str | None = None) -> ModuleType:
    """Import `module` (default `name`) or raise an ImportError that says `pip install openfly-agent[extra]`."""
    try:
        return importlib.import_module(module or name)
    except ImportError as err:
        raise ImportError(
            f"'{name}' is needed for this feature but is not installed: "
            f"pip install 'openfly-agent[{extra}]' (or pip install {name})"
        ) from err

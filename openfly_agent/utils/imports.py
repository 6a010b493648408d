"""Lazy imports: optional dependencies (with an error naming the extra to install) and package exports."""

from __future__ import annotations

import importlib
from collections.abc import Callable
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


def lazy_exports(package: str, exports: dict[str, str]) -> Callable[[str], object]:
    """A module-level `__getattr__` for `package`: `exports[name]` is the submodule imported on first access.

    Usage in a package's `__init__.py`: `__getattr__ = lazy_exports(__name__, _EXPORTS)`.
    """

    def __getattr__(name: str):
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{exports[name]}"), name)

    return __getattr__

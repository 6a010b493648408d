"""Level-1 model: the agent (agent.py: loss, processor, save / load) around its network (network.py: encode,
decode), the closed-loop session (session.py) and the components by sub-package: vision/, grounding/, memory/,
language/, persistence/ (checkpoint folders).

Callers import the module they need (`from openfly_agent.model.agent import OpenFlyAgent`). For a user of a
saved checkpoint the package re-exports the agent and `register_auto_classes` (`from openfly_agent.model import
OpenFlyAgent`, docs/RELEASE.md), imported on first use so that `import openfly_agent.model` stays cheap.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "OpenFlyAgent": ".agent",
    "register_auto_classes": ".agent",
}

__all__ = list(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

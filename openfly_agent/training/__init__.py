"""Level-2 training: config, loop, optimizer and schedule, checkpoints, evaluation, export.

`fit(build_run(cfg))` is what train.py does. Names are imported lazily (importing the package is free).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "TrainConfig": "config",
    "build_run": "builder",
    "fit": "loop",
    "TrainingRun": "loop",
    "FitResult": "loop",
    "PreflightError": "preflight",
    "CheckpointManager": "checkpoint",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)

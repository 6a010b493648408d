"""Level-2 training: config, loop, optimizer and schedule, checkpoints, evaluation, export.

`fit(build_run(cfg))` is what train.py does. Names are imported lazily (importing the package is free).
"""

from __future__ import annotations

from openfly_agent.utils.imports import lazy_exports

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

__getattr__ = lazy_exports(__name__, _EXPORTS)

"""Level-2 training: config, the `train(cfg)` run, optimizer and schedule, checkpoints, evaluation, export.

`train(cfg)` (training/trainer.py) is what train.py does. Names are imported lazily (importing the package is
free).
"""

from __future__ import annotations

from openfly_agent.utils.imports import lazy_exports

_EXPORTS = {  # what train.py imports
    "train": "trainer",
    "TrainResult": "finish",
    "PreflightError": "preflight",
}

__all__ = sorted(_EXPORTS)

__getattr__ = lazy_exports(__name__, _EXPORTS)

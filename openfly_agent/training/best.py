"""`checkpoint.keep_best`: whether a validation pass is the best so far, and the record that lets a resume know.

The checkpoint a best pass saves holds `best_metric.json` (metric, value, step); `checkpoints/best` names that
checkpoint (training/checkpoint.py), so a resumed run reads the best value so far from the folder `best` names
and only a better pass moves it. Every process decides alike: the validation figures are reduced over the
processes and the record is read from the shared run folder.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

BEST_RECORD_NAME = "best_metric.json"


@dataclass
class BestMetric:
    """The best value of one validation figure so far (`metric` as logged, e.g. "val/loss") and its step."""

    metric: str
    value: float | None = None
    step: int | None = None

    @property
    def lower_is_better(self) -> bool:
        return self.metric.endswith("loss")

    def offer(self, figures: dict[str, float], step: int) -> bool:
        """Take the pass's `figures` (validation figures without the `val/` prefix) at `step`; True (and the new
        best kept) when they beat the best so far. A pass without the figure, or NaN, never does."""
        value = figures.get(self.metric.split("/", 1)[1])
        if value is None or math.isnan(value):
            return False
        if self.value is not None:
            better = value < self.value if self.lower_is_better else value > self.value
            if not better:
                return False
        self.value, self.step = float(value), step
        return True

    def record(self) -> dict:
        """What the best pass's checkpoint keeps (`BEST_RECORD_NAME`)."""
        return {"metric": self.metric, "value": self.value, "step": self.step}

    @classmethod
    def resume(cls, metric: str, checkpoint: Path | None) -> BestMetric:
        """The best so far of `metric`: read from the record in `checkpoint` (what `best` names; None: a fresh
        start). A record of another metric starts afresh, with a warning."""
        best = cls(metric)
        if checkpoint is None or not (checkpoint / BEST_RECORD_NAME).is_file():
            return best
        record = json.loads((checkpoint / BEST_RECORD_NAME).read_text())
        if record.get("metric") != metric:
            logger.warning(
                "checkpoint.keep_best=%s, but %s is the best by %s: the next validation pass becomes the best",
                metric,
                checkpoint,
                record.get("metric"),
            )
            return best
        best.value, best.step = float(record["value"]), int(record["step"])
        return best

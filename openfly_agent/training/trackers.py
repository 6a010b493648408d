"""Experiment trackers through accelerate: TensorBoard (default), W&B (optional), always a JSON-lines file."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from accelerate.tracking import GeneralTracker

from openfly_agent.utils.imports import require_package

METRICS_FILE_NAME = "metrics.jsonl"
TRACKERS = ("tensorboard", "wandb", "none")


class JsonlTracker(GeneralTracker):
    """Appends one JSON object per `log` call to `<logging_dir>/metrics.jsonl` (main process only).

    The file is the machine-readable record of a run: tests and `bench/` read it, and it survives without
    TensorBoard. On resume it is appended to, so a resumed run's file holds the whole history (a step logged
    twice means the run was interrupted after that step and before its next checkpoint).
    """

    name = "jsonl"
    requires_logging_directory = True
    main_process_only = True

    def __init__(self, run_name: str, logging_dir: str | Path) -> None:
        super().__init__()
        self.run_name = run_name
        self.path = Path(logging_dir) / METRICS_FILE_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)

    @property
    def tracker(self) -> Path:
        return self.path

    def store_init_configuration(self, values: dict) -> None:
        self._append({"event": "config", "run_name": self.run_name, "config": values})

    def log(self, values: dict, step: int | None = None, **kwargs: Any) -> None:
        record = {"step": step}
        record.update({k: _jsonable(v) for k, v in values.items()})
        self._append(record)

    def _append(self, record: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def make_trackers(kind: str, run_name: str, logging_dir: str | Path) -> list:
    """The `log_with` list for `Accelerator`: the JSON-lines tracker plus `kind` (tensorboard|wandb|none)."""
    if kind not in TRACKERS:
        raise ValueError(f"logging.tracker must be one of {TRACKERS}, got {kind!r}")
    trackers: list = [JsonlTracker(run_name, logging_dir)]
    if kind == "wandb":
        require_package("wandb", extra="wandb")
    if kind != "none":
        trackers.append(kind)
    return trackers


def read_metrics(logging_dir: str | Path) -> list[dict]:
    """The records of `metrics.jsonl` (config events excluded), in the order they were written.

    Raises:
        ValueError: a line is not JSON (the file and the line number).
    """
    path = Path(logging_dir) / METRICS_FILE_NAME
    if not path.is_file():
        return []
    records = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}, line {number}: not valid JSON ({err})") from err
    return [r for r in records if r.get("event") != "config"]

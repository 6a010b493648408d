"""Experiment trackers through accelerate: TensorBoard (default), W&B (optional), always a JSON-lines file.

A resumed run logs again the steps its interrupted predecessor logged after the checkpoint it resumes from;
`start_trackers` drops those first (each step is recorded once): metrics.jsonl is rewritten without them and
TensorBoard purges them (its `purge_step`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import yaml
from accelerate import Accelerator
from accelerate.tracking import GeneralTracker

from openfly_agent.utils.files import write_text_atomic
from openfly_agent.utils.imports import require_package

METRICS_FILE_NAME = "metrics.jsonl"
TRACKERS = ("tensorboard", "wandb", "none")


class JsonlTracker(GeneralTracker):
    """Appends one JSON object per `log` call to `<logging_dir>/metrics.jsonl` (main process only).

    The file is the machine-readable record of a run: tests and `bench/` read it, and it survives without
    TensorBoard. On resume it is appended to, so a resumed run's file holds the whole history, each step once:
    with `resumed_at` set (the checkpoint's step) `start` first drops the records of later steps, which the
    interrupted run logged before it stopped and the resumed run logs again.
    """

    name = "jsonl"
    requires_logging_directory = True
    main_process_only = True

    def __init__(self, run_name: str, logging_dir: str | Path) -> None:
        super().__init__()
        self.run_name = run_name
        self.path = Path(logging_dir) / METRICS_FILE_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.resumed_at: int | None = None

    @property
    def tracker(self) -> Path:
        return self.path

    def start(self) -> None:
        if self.resumed_at is None or not self.path.is_file():
            return
        lines = self.path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if not _logged_after(line, self.resumed_at)]
        if len(kept) < len(lines):
            write_text_atomic(self.path, "".join(kept))

    def store_init_configuration(self, values: dict) -> None:
        self._append({"event": "config", "run_name": self.run_name, "config": values})

    def log(self, values: dict, step: int | None = None, **kwargs: Any) -> None:
        record = {"step": step}
        record.update({k: _jsonable(v) for k, v in values.items()})
        self._append(record)

    def _append(self, record: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")


def _logged_after(line: str, step: int) -> bool:
    """Whether a metrics.jsonl line records a step after `step` (config events and unreadable lines: no)."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError:
        return False
    return isinstance(record, dict) and isinstance(record.get("step"), int) and record["step"] > step


class TensorBoardTracker(GeneralTracker):
    """TensorBoard in `<logging_dir>/<project>/`: one run, with the hyperparameters in its own event file.

    accelerate's tracker writes them with `add_hparams`, which makes a run folder of its own for every start
    (a second, empty "run" in TensorBoard each time), and its `hparams.yml` into another timestamped folder.
    Here they go into the run's events and `<project>/hparams.yml`. With `resumed_at` set, the steps logged
    after it are purged.
    """

    name = "tensorboard"
    requires_logging_directory = True
    main_process_only = True

    def __init__(self, project: str, logging_dir: str | Path) -> None:
        super().__init__()
        self.run_dir = Path(logging_dir) / project
        self.resumed_at: int | None = None
        self.writer = None

    def start(self) -> None:
        from torch.utils.tensorboard import SummaryWriter  # lazy: only the runs that use TensorBoard

        purge = None if self.resumed_at is None else self.resumed_at + 1
        self.writer = SummaryWriter(str(self.run_dir), purge_step=purge)

    @property
    def tracker(self):
        return self.writer

    def store_init_configuration(self, values: dict) -> None:
        from torch.utils.tensorboard.summary import hparams  # lazy: as in `start`

        for summary in hparams(values, metric_dict={}):  # experiment, session start and end
            self.writer.file_writer.add_summary(summary)
        self.writer.flush()
        (self.run_dir / "hparams.yml").write_text(yaml.safe_dump(values))

    def log(self, values: dict, step: int | None = None, **kwargs: Any) -> None:
        for key, value in values.items():
            if isinstance(value, (int, float)):
                self.writer.add_scalar(key, value, global_step=step)
            elif isinstance(value, str):
                self.writer.add_text(key, value, global_step=step)
        self.writer.flush()

    def finish(self) -> None:
        if self.writer is not None:
            self.writer.close()


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def make_trackers(kind: str, run_name: str, logging_dir: str | Path, project: str) -> list:
    """The `log_with` list for `Accelerator`: the JSON-lines tracker plus `kind` (tensorboard|wandb|none);
    TensorBoard writes to `<logging_dir>/<project>/`."""
    if kind not in TRACKERS:
        raise ValueError(f"logging.tracker must be one of {TRACKERS}, got {kind!r}")
    trackers: list = [JsonlTracker(run_name, logging_dir)]
    if kind == "tensorboard":
        trackers.append(TensorBoardTracker(project, logging_dir))
    elif kind == "wandb":
        require_package("wandb", extra="wandb")
        trackers.append(kind)
    return trackers


def start_trackers(accelerator: Accelerator, project: str, config: dict, resumed_at: int | None) -> None:
    """`accelerator.init_trackers(project, config)`; `resumed_at`: the step of the checkpoint a resumed run
    starts from (None for a new run), after which what was logged is dropped (module docstring)."""
    for tracker in accelerator.log_with:
        if isinstance(tracker, (JsonlTracker, TensorBoardTracker)):
            tracker.resumed_at = resumed_at
    accelerator.init_trackers(project, config=config)


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

"""Resuming a run only with the settings it was trained with, and a record of what a resume changed.

`<output_dir>/train_config.json` keeps the settings of the run's first steps; every checkpoint folder holds the
settings its own steps ran with. `--resume=true` compares the new settings with the checkpoint's: a change of
anything that decides what is learned (data, model, optimizer, batch, seed, ...) is refused, naming each
setting, so the record never mixes two recipes silently. The settings in `RESUMABLE_KEYS` (how long, how
often to log / validate / save, on which split to validate, where and with what resources) may change; each
change is appended to `<output_dir>/config_changes.jsonl` with the step and time it took effect
(docs/TRAINING.md, "Resuming").
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from openfly_agent.constants import TRAIN_CONFIG_NAME
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.preflight import PreflightError
from openfly_agent.training.state import TrainerState
from openfly_agent.utils.config import (
    changed_settings,
    config_to_dict,
    describe_changes,
    flat_settings,
    is_listed,
    save_config,
)

CONFIG_CHANGES_NAME = "config_changes.jsonl"

# Dotted keys (or sections, ending in ".") a resume may change: they decide how long the run goes, what is
# logged, validated and saved, and where and with which resources it runs, not what a step learns.
RESUMABLE_KEYS = (
    "steps", "epochs", "time_limit_minutes", "resume", "output_dir", "cpu",
    "gradient_checkpointing", "compile_layers", "optim.fused_adamw", "batch.per_device_batch_size", "logging.",
    "validation.", "checkpoint.",
    "data.num_workers", "data.cache_episodes", "data.cache_frames", "data.val_split", "lora.merge_at_end",
)  # fmt: skip


def resume_changes(cfg: TrainConfig, checkpoint: Path | None) -> dict[str, tuple]:
    """The settings this resume changes (all in `RESUMABLE_KEYS`): `{dotted key: (old, new)}`.

    Compared with the settings of `checkpoint` (its train_config.json, else the run's); a fresh run (None) or a
    checkpoint with neither changes nothing.

    Raises:
        PreflightError: a setting outside `RESUMABLE_KEYS` differs; the message lists every one.
    """
    if checkpoint is None:
        return {}
    stored_path = next(
        (
            p
            for p in (checkpoint / TRAIN_CONFIG_NAME, Path(cfg.output_dir) / TRAIN_CONFIG_NAME)
            if p.is_file()
        ),
        None,
    )
    if stored_path is None:
        return {}
    try:
        stored = json.loads(stored_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise PreflightError(
            f"{stored_path} is not readable ({err}): cannot check the resumed settings"
        ) from err
    current = config_to_dict(cfg)
    # settings the checkpoint does not record (a field added to TrainConfig since) are not compared
    recorded = set(flat_settings(stored)) & set(flat_settings(current))
    changes = {k: v for k, v in changed_settings(stored, current).items() if k in recorded}
    refused = {k: v for k, v in changes.items() if not is_listed(k, RESUMABLE_KEYS)}
    if refused:
        raise PreflightError(
            f"--resume=true with other settings than {stored_path} ({describe_changes(refused, limit=12)}): "
            "resume with the run's settings, or train in a new --output_dir (docs/TRAINING.md lists the "
            "settings a resume may change)"
        )
    return {k: v for k, v in changes.items() if k != "resume"}


def record_run_settings(cfg: TrainConfig, checkpoint: Path | None, changes: dict[str, tuple]) -> None:
    """A fresh run writes `<output_dir>/train_config.json`; a resume keeps it (the first steps' settings, unless
    a run from before this record had none) and appends its changes to `config_changes.jsonl`. Main process."""
    folder = Path(cfg.output_dir)
    if checkpoint is None or not (folder / TRAIN_CONFIG_NAME).is_file():
        save_config(cfg, folder / TRAIN_CONFIG_NAME)
    if checkpoint is None or not changes:
        return
    entry = {
        "step": TrainerState.load(checkpoint).step,
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "checkpoint": checkpoint.name,
        "changes": {key: {"from": old, "to": new} for key, (old, new) in changes.items()},
    }
    with open(folder / CONFIG_CHANGES_NAME, "a") as f:
        f.write(json.dumps(entry, sort_keys=True) + "\n")

"""The checkpoint folder behind what a user passes: a step folder, a training run or its `last` pointer.

A training run writes `<run>/checkpoints/step-NNNNNN/` (Hugging Face folders) and `<run>/checkpoints/last`, a
one-line file naming the newest complete one (training/checkpoint.py).
"""

from __future__ import annotations

import json
from pathlib import Path

from openfly_agent.constants import (
    ADAPTER_DIR_NAME,
    CHECKPOINTS_DIR,
    CONFIG_NAME,
    LAST_POINTER_NAME,
    WEIGHTS_INDEX_NAME,
    WEIGHTS_NAME,
)


def resolve_checkpoint_folder(path: str | Path) -> Path | None:
    """The folder holding `config.json` for `path`; None when `path` does not exist locally (a Hub repo id).

    Accepts a checkpoint folder (as is), the `last` pointer file, `<run>/checkpoints` or the run folder `<run>`
    (both followed to the step folder `last` names).

    Raises:
        FileNotFoundError: `path` exists but is none of these (or its pointer names a missing folder).
    """
    start = path = Path(path)
    if not path.exists():
        return None
    for _ in range(3):  # run folder -> checkpoints folder -> pointer file -> step folder
        if path.is_dir() and (path / CONFIG_NAME).is_file():
            return path
        if path.is_file():  # a pointer: one line naming a checkpoint folder beside it
            path = path.parent / path.read_text().strip()
        elif (path / LAST_POINTER_NAME).is_file():
            path = path / LAST_POINTER_NAME
        elif (path / CHECKPOINTS_DIR / LAST_POINTER_NAME).is_file():
            path = path / CHECKPOINTS_DIR / LAST_POINTER_NAME
        else:
            break
    if path.is_dir() and (path / CONFIG_NAME).is_file():
        return path
    raise FileNotFoundError(
        f"{start} is not a checkpoint folder (no {CONFIG_NAME}) nor a training run: pass a checkpoint folder "
        f"(<run>/{CHECKPOINTS_DIR}/step-NNNNNN), the pointer <run>/{CHECKPOINTS_DIR}/{LAST_POINTER_NAME} or the "
        "training run folder <run>"
    )


def check_not_adapter_only(folder: Path) -> None:
    """A LoRA training checkpoint holds the adapter only (no base weights): say what loads it."""
    has_weights = (folder / WEIGHTS_NAME).is_file() or (folder / WEIGHTS_INDEX_NAME).is_file()
    if not has_weights and (folder / ADAPTER_DIR_NAME).is_dir():
        raise ValueError(
            f"{folder} is a LoRA checkpoint (adapter only, no base weights): load it with "
            "openfly_agent.model.lora_checkpoint.load_lora_agent(checkpoint, base=<the init checkpoint>), or load "
            "<output_dir>/merged, the full model a LoRA run writes at the end (lora.merge_at_end)"
        )


def checkpoint_files(folder: Path) -> list[Path]:
    """The safetensors files of a checkpoint folder (the shards its index names, or its one file).

    Raises:
        FileNotFoundError: the folder holds neither.
    """
    if (folder / WEIGHTS_INDEX_NAME).is_file():
        shards = sorted(set(json.loads((folder / WEIGHTS_INDEX_NAME).read_text())["weight_map"].values()))
        return [folder / shard for shard in shards]
    if (folder / WEIGHTS_NAME).is_file():
        return [folder / WEIGHTS_NAME]
    raise FileNotFoundError(f"{folder} has neither {WEIGHTS_NAME} nor {WEIGHTS_INDEX_NAME}")

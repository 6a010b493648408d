"""The checkpoint folder behind what a user passes: a step folder, a training run or its `last` pointer.

A training run writes `<run>/checkpoints/step-NNNNNN/` (Hugging Face folders) and `<run>/checkpoints/last`, a
relative symlink to the newest complete one (training/checkpoint.py), so every loader that opens a folder opens
`last`. Runs written before kept `last` as a one-line file naming that folder; both are read.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from openfly_agent.constants import (
    ADAPTER_DIR_NAME,
    CHECKPOINTS_DIR,
    CONFIG_NAME,
    LAST_POINTER_NAME,
    MERGED_DIR_NAME,
    STAGE_GROUNDING,
    STAGE_NAVIGATION,
    TRAIN_CONFIG_NAME,
    WEIGHTS_INDEX_NAME,
    WEIGHTS_NAME,
)


def resolve_checkpoint_folder(path: str | Path) -> Path | None:
    """The folder holding `config.json` for `path`; None when `path` does not exist locally (a Hub repo id).

    Accepts a checkpoint folder (as is), the `last` pointer (a symlink, or an older run's pointer file),
    `<run>/checkpoints` or the run folder `<run>` (all followed to the step folder `last` names).

    Raises:
        FileNotFoundError: `path` exists but is none of these (or its pointer names a missing folder).
    """
    start = path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return None
    for _ in range(3):  # run folder -> checkpoints folder -> `last` -> step folder
        pointed = last_pointer_target(path)
        if pointed is not None:  # `last` itself: the step folder it names
            path = pointed
        elif path.is_dir() and (path / CONFIG_NAME).is_file():
            return path
        elif _is_last_pointer(path / LAST_POINTER_NAME):
            path = path / LAST_POINTER_NAME
        elif _is_last_pointer(path / CHECKPOINTS_DIR / LAST_POINTER_NAME):
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


def last_pointer_target(pointer: Path) -> Path | None:
    """The step folder a `last` pointer names (a symlink, or an older run's one-line file); None when `pointer`
    is neither (a folder, or nothing). The target need not exist."""
    pointer = Path(pointer)
    if pointer.name != LAST_POINTER_NAME:
        return None
    if pointer.is_symlink():
        return pointer.parent / os.readlink(pointer)
    if pointer.is_file():
        return pointer.parent / pointer.read_text().strip()
    return None


def _is_last_pointer(path: Path) -> bool:
    """`<run>/checkpoints/last`: a symlink to the step folder, or (runs written before) a one-line file."""
    return path.is_symlink() or path.is_file()


def check_navigation_stage(folder: Path) -> None:
    """Refuse a grounding-stage checkpoint where an agent is wanted (eval.py, a release): its action head was
    never trained. Read from the folder's train_config.json `stage`; folders without one pass.

    Raises:
        ValueError: one line naming the folder, its stage and the navigation stage to pass instead.
    """
    folder = Path(folder)
    train_config = folder / TRAIN_CONFIG_NAME
    try:
        stage = json.loads(train_config.read_text()).get("stage") if train_config.is_file() else None
    except (OSError, json.JSONDecodeError, AttributeError):
        return  # not ours to judge here: the loaders name an unreadable file
    if stage != STAGE_GROUNDING:
        return
    run = folder.parent.parent if folder.parent.name == CHECKPOINTS_DIR else folder
    sibling = run.parent / STAGE_NAVIGATION
    instead = (
        f"the navigation stage trained from it, e.g. {sibling}"
        if sibling.is_dir()
        else f"the checkpoint of a {STAGE_NAVIGATION} stage started from it (train.py --init.checkpoint={run})"
    )
    raise ValueError(
        f"{folder} is a {STAGE_GROUNDING}-stage checkpoint ({TRAIN_CONFIG_NAME}: stage={STAGE_GROUNDING}, no "
        f"trained action head), not an agent: pass {instead}"
    )


def check_not_adapter_only(folder: Path, given: str | Path | None = None) -> None:
    """A LoRA training checkpoint holds the adapter only (no base weights): say what loads it instead, the run's
    merged model (`<run>/merged`, what eval.py and the release load) by its path.

    Args:
        folder: the checkpoint folder `given` resolved to.
        given: what the user passed (a run folder or its `last` pointer), named in the message; default `folder`.

    Raises:
        ValueError: one line naming `given`, the merged model to load and the adapter loader.
    """
    has_weights = (folder / WEIGHTS_NAME).is_file() or (folder / WEIGHTS_INDEX_NAME).is_file()
    if has_weights or not (folder / ADAPTER_DIR_NAME).is_dir():
        return
    given = Path(given) if given is not None else folder
    what = (
        f"{folder} is a LoRA checkpoint (adapter only, no base weights)"
        if given == folder
        else f"{given} is a LoRA training run: its checkpoint {folder} holds the adapter only (no base weights)"
    )
    run = folder.parent.parent if folder.parent.name == CHECKPOINTS_DIR else None
    merged = run / MERGED_DIR_NAME if run is not None else Path("<output_dir>") / MERGED_DIR_NAME
    written = (merged / CONFIG_NAME).is_file()
    merged_text = (
        f"load {merged}, the full model the run merged at the end"
        if written
        else f"load {merged}, the full model a LoRA run writes at the end (lora.merge_at_end), once it is there"
    )
    raise ValueError(
        f"{what}: {merged_text}; or load the adapter on its base with "
        "openfly_agent.model.persistence.lora_checkpoint.load_lora_agent(checkpoint, base=<the init checkpoint>)"
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


class UnreadableWeightsError(ValueError):
    """A safetensors file that cannot be read (truncated or corrupt); the message names the file."""


@contextmanager
def open_safetensors(path: str | Path) -> Iterator:
    """`safetensors.safe_open(path)` whose failure (a truncated or corrupt file) is one `UnreadableWeightsError`
    naming the file, not the library's error from deep inside a loader."""
    from safetensors import SafetensorError, safe_open

    try:
        handle = safe_open(str(path), framework="pt")
    except (SafetensorError, OSError) as err:
        raise UnreadableWeightsError(
            f"{path} is not a readable safetensors file ({err}): it is truncated or corrupt; copy or download "
            "it again"
        ) from None
    with handle:
        yield handle


def check_weights_readable(folder: Path) -> None:
    """Read the header of every safetensors file of `folder` (nothing when it has none): the header lists every
    tensor's byte range, so a truncated copy fails here, before a loader starts or an output folder is made.

    Raises:
        UnreadableWeightsError: a file that is truncated or corrupt, named.
    """
    try:
        files = checkpoint_files(Path(folder))
    except (FileNotFoundError, json.JSONDecodeError, KeyError):  # no weights, a bad index: the loader says so
        return
    for path in files:
        if path.is_file():
            with open_safetensors(path):
                pass

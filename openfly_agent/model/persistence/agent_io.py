"""What the agent's save / load adds to transformers': the processor files beside the weights, the checks of
a folder before it loads, and the tokenizer saved with it (used by `OpenFlyAgent.save_pretrained` /
`from_pretrained`, model/agent.py)."""

from __future__ import annotations

import json
from pathlib import Path

from torch import nn

from openfly_agent.constants import ACTION_TOKENIZER_NAME, NORM_STATS_NAME
from openfly_agent.model.language.lora import has_lora
from openfly_agent.model.language.tokenizer import load_tokenizer, tokenizer_folder
from openfly_agent.model.persistence.checkpoint_path import (
    check_not_adapter_only,
    check_weights_readable,
    resolve_checkpoint_folder,
)


def check_no_lora(agent: nn.Module) -> None:
    """Raise when LoRA is attached: the plain key layout is saved only once it is merged."""
    if has_lora(agent):
        raise ValueError(
            "LoRA is attached: merge it first (model.lora.merge_lora) or save the adapter "
            "(model.lora.save_lora_adapter); the merged agent saves in the plain key layout"
        )


def save_processor_files(agent: nn.Module, folder: str | Path) -> None:
    """What prepares inputs and reads outputs of `agent` (an `OpenFlyAgent`): the processor (processor_config.json
    + tokenizer files), action_tokenizer.json and the norm stats (dataset_statistics.json)."""
    folder = Path(folder)
    agent.action_tokenizer.save(folder / ACTION_TOKENIZER_NAME)
    if agent.config.norm_stats:
        (folder / NORM_STATS_NAME).write_text(json.dumps(agent.config.norm_stats, indent=2) + "\n")
    if agent.processor is not None:
        agent.processor.save_pretrained(str(folder))


def loadable_checkpoint(name: str) -> str:
    """The folder or Hub id transformers loads for `name`: a training run, `<run>/checkpoints` or the
    `checkpoints/last` pointer give the newest checkpoint; a LoRA checkpoint (`adapter/`, no weights) raises
    with what to load instead, a truncated or corrupt weights file `UnreadableWeightsError` naming it."""
    folder = resolve_checkpoint_folder(name)
    if folder is None:
        return name
    check_not_adapter_only(folder, given=name)
    check_weights_readable(folder)  # a truncated file: one line naming it
    return str(folder)


def saved_tokenizer(name: str, kwargs: dict):
    """The tokenizer saved beside the weights of `name` (folder or Hub id; `kwargs` of from_pretrained), or None."""
    saved = tokenizer_folder(name, kwargs)
    return load_tokenizer(saved) if saved is not None else None

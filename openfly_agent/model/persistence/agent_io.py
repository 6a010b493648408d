"""How the agent is saved and loaded: transformers' safetensors folders plus the processor files and remote code.

`AgentPersistence` is a mixin of `OpenFlyAgent` (model/agent.py), placed before `PreTrainedModel`.
"""

from __future__ import annotations

import json
from pathlib import Path

from openfly_agent.constants import ACTION_TOKENIZER_NAME, NORM_STATS_NAME
from openfly_agent.model.language.tokenizer import load_tokenizer, tokenizer_folder
from openfly_agent.model.persistence.checkpoint_path import (
    check_not_adapter_only,
    check_weights_readable,
    resolve_checkpoint_folder,
)
from openfly_agent.model.persistence.remote_code import write_remote_code


class AgentPersistence:
    """`save_pretrained` / `from_pretrained` with the processor, action tokenizer, norm stats and remote code."""

    # --- persistence ------------------------------------------------------------------------------
    def save_pretrained(self, save_directory, *args, **kwargs) -> None:
        """transformers' save (config.json + safetensors), then the processor files and the remote code."""
        if getattr(self.language_model, "peft_config", None) is not None:
            raise ValueError(
                "LoRA is attached: merge it first (model.lora.merge_lora) or save the adapter "
                "(model.lora.save_lora_adapter); the merged agent saves in the plain key layout"
            )
        # transformers would upload before the extra files exist: push the finished folder afterwards instead
        push = kwargs.pop("push_to_hub", False)
        hub = {k: kwargs.pop(k) for k in ("repo_id", "commit_message", "create_pr", "private") if k in kwargs}
        super().save_pretrained(save_directory, *args, **kwargs)
        if not kwargs.get("is_main_process", True):
            return
        folder = Path(save_directory)
        self.save_processor_files(folder)
        write_remote_code(folder)
        if push:
            hub.update({k: kwargs[k] for k in ("token", "max_shard_size") if k in kwargs})
            self.push_to_hub(hub.pop("repo_id", folder.name), **hub)

    def save_processor_files(self, folder: str | Path) -> None:
        """What prepares inputs and reads outputs: the processor (processor_config.json + tokenizer files),
        action_tokenizer.json and the norm stats (dataset_statistics.json)."""
        folder = Path(folder)
        self.action_tokenizer.save(folder / ACTION_TOKENIZER_NAME)
        if self.config.norm_stats:
            (folder / NORM_STATS_NAME).write_text(json.dumps(self.config.norm_stats, indent=2) + "\n")
        if self.processor is not None:
            self.processor.save_pretrained(str(folder))

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, *args, tokenizer=None, **kwargs):
        """transformers' load, plus the tokenizer saved beside the weights (folder or Hub repo id).

        Also takes a training run folder, `<run>/checkpoints` or the `checkpoints/last` pointer: they load the
        newest checkpoint. A LoRA checkpoint (`adapter/`, no weights) raises with what to load instead; a
        truncated or corrupt weights file raises `UnreadableWeightsError` naming it.
        """
        name = str(pretrained_model_name_or_path)
        folder = resolve_checkpoint_folder(name)
        if folder is not None:
            name = str(folder)
            check_not_adapter_only(folder)
            check_weights_readable(folder)  # a truncated file: one line naming it
        loaded = super().from_pretrained(name, *args, **kwargs)
        model = loaded[0] if isinstance(loaded, tuple) else loaded
        if tokenizer is None:
            saved = tokenizer_folder(name, kwargs)
            tokenizer = load_tokenizer(saved) if saved is not None else None
        model.tokenizer = tokenizer
        return loaded

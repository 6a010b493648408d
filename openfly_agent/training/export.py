"""A checkpoint's Hugging Face folder: weights (or LoRA adapter), config, processor files, train config.

State dicts are gathered with `accelerator.get_state_dict` (a collective under FSDP / ZeRO-3: every process
calls the exporter) and written by rank 0. A LoRA run can also be merged at the end, on rank 0 and on the CPU,
from that in-memory state dict: the base model is never loaded a second time.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

from accelerate import Accelerator
from safetensors.torch import save_file
from torch import nn

from openfly_agent import constants as C
from openfly_agent.model.language.lora import TRAINABLE_PARTS, TRAINABLES_NAME, has_lora
from openfly_agent.model.persistence.agent_io import save_processor_files
from openfly_agent.model.persistence.remote_code import remove_auto_map, write_remote_code
from openfly_agent.model.persistence.saved_names import saved_state_dict
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.lora import lora_scalings, merge_lora_state_dict
from openfly_agent.utils.config import save_config
from openfly_agent.utils.file_modes import follow_umask

logger = logging.getLogger(__name__)

MAX_SHARD_SIZE = "5GB"


def export_model_folder(accelerator: Accelerator, model: nn.Module, folder: Path, cfg: TrainConfig) -> None:
    """Write the model folder of the current weights into `folder` (call on every process: the state-dict
    gather is a collective under FSDP / ZeRO-3; rank 0 writes)."""
    state_dict = accelerator.get_state_dict(model)
    if not accelerator.is_main_process:
        return
    agent = accelerator.unwrap_model(model)
    if has_lora(agent):
        write_lora_folder(agent, state_dict, folder)
    else:
        agent.save_pretrained(str(folder), state_dict=state_dict, safe_serialization=True)
    save_config(cfg, Path(folder) / C.TRAIN_CONFIG_NAME)


def write_model_metadata(agent: nn.Module, folder: Path) -> None:
    """Everything of a model folder but the weights: config.json and the processor files (processor config,
    tokenizer, action tokenizer, norm stats). No `auto_map` (a config loaded from a checkpoint carries one) until
    the `trust_remote_code` modules are written too."""
    folder.mkdir(parents=True, exist_ok=True)
    agent.config.save_pretrained(str(folder))
    remove_auto_map(folder)
    save_processor_files(agent, folder)


def write_lora_folder(agent: nn.Module, state_dict: dict, folder: Path) -> Path:
    """Model metadata + `adapter/` (peft files of the LLM + the projector / grounding head tensors).

    The layout of `model.lora.save_lora_adapter`, so `model.lora.load_lora_adapter` reads it; written from the
    gathered `state_dict` so it also works when the live parameters are sharded. The `trust_remote_code` files
    make `AutoModel.from_pretrained` say how to load it (the adapter needs its base weights).
    """
    write_model_metadata(agent, Path(folder))
    write_remote_code(folder)
    out = Path(folder) / C.ADAPTER_DIR_NAME
    state_dict = saved_state_dict(state_dict)  # `language_model.*`, `projector.*`, ... as on disk
    prefix = "language_model."
    llm_state = {k[len(prefix) :]: v for k, v in state_dict.items() if k.startswith(prefix)}
    agent.network.language_model.save_pretrained(str(out), state_dict=llm_state)
    trainables = {k: v.contiguous() for k, v in state_dict.items() if k.split(".", 1)[0] in TRAINABLE_PARTS}
    save_file(trainables, str(out / TRAINABLES_NAME))
    return out


def export_merged_lora(accelerator: Accelerator, model: nn.Module, output_dir: str | Path) -> Path | None:
    """Merge the LoRA adapters into the base weights on rank 0, on the CPU, and write `<output_dir>/merged`.

    Every process joins the state-dict gather; only rank 0 merges and writes (atomically: a staging folder
    renamed into place). Returns the folder on rank 0, None elsewhere.
    """
    from huggingface_hub import save_torch_state_dict

    state_dict = accelerator.get_state_dict(model)
    if not accelerator.is_main_process:
        return None
    agent = accelerator.unwrap_model(model)
    merged = saved_state_dict(merge_lora_state_dict(state_dict, lora_scalings(agent)))
    final = Path(output_dir) / C.MERGED_DIR_NAME
    staging = Path(output_dir) / f".tmp-{C.MERGED_DIR_NAME}"
    if staging.exists():
        shutil.rmtree(staging)
    write_model_metadata(agent, staging)
    save_torch_state_dict(merged, str(staging), max_shard_size=MAX_SHARD_SIZE)
    write_remote_code(staging)
    follow_umask(staging)  # safetensors writes 0600
    if final.exists():
        shutil.rmtree(final)
    os.replace(staging, final)
    logger.info("merged LoRA model written to %s (load it with OpenFlyAgent.from_pretrained)", final)
    return final

"""LoRA checkpoints (metadata + `adapter/`, no base weights): what to load for one, and the agent it gives.

A LoRA run writes adapter-only checkpoints and, at the end, `<output_dir>/merged`, the full merged model
(lora.merge_at_end). `checkpoint_weights` says what a checkpoint folder stands for: its own weights, the run's
merged model, or the adapter on its base; eval.py and the model release load through it. Users loading an
adapter release: `load_lora_agent("<adapter repo or folder>", base="<base repo or folder>")`.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from openfly_agent.constants import (
    ADAPTER_DIR_NAME,
    CHECKPOINTS_DIR,
    CONFIG_NAME,
    LAST_POINTER_NAME,
    MERGED_DIR_NAME,
    MODEL_TYPE,
    TRAIN_CONFIG_NAME,
    WEIGHTS_INDEX_NAME,
    WEIGHTS_NAME,
)
from openfly_agent.model.language.tokenizer import load_tokenizer
from openfly_agent.model.persistence.checkpoint_path import last_pointer_target

logger = logging.getLogger(__name__)

BASE_OURS, BASE_OPENVLA = "openfly_agent", "openvla"


def is_lora_checkpoint(folder: Path) -> bool:
    """Whether `folder` holds a LoRA adapter (`adapter/adapter_config.json`) instead of full weights."""
    return (Path(folder) / ADAPTER_DIR_NAME / "adapter_config.json").is_file()


@dataclass
class CheckpointWeights:
    """What to load for a checkpoint folder: `folder`'s full weights, or its LoRA adapter on `base`."""

    folder: Path
    base: str | None = None  # the base weights (folder or Hub id) of an adapter-only folder
    description: str = ""  # for the log: which of the two, and why


def _read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def has_full_weights(folder: Path) -> bool:
    """Whether `folder` holds the model's weights (one safetensors file or an index of shards)."""
    return (folder / WEIGHTS_NAME).is_file() or (folder / WEIGHTS_INDEX_NAME).is_file()


def merged_model_of(folder: Path) -> Path | None:
    """`<output_dir>/merged` of the LoRA run whose newest checkpoint is `folder`, when the run wrote it after that
    checkpoint (a resumed run that stopped early leaves an older merge behind); None otherwise."""
    checkpoints = folder.parent
    newest = (
        last_pointer_target(checkpoints / LAST_POINTER_NAME) if checkpoints.name == CHECKPOINTS_DIR else None
    )
    if newest is None or newest.resolve() != folder.resolve():
        return None  # not a run's checkpoint, or an older step: the merge holds the last one
    merged = checkpoints.parent / MERGED_DIR_NAME
    if not (merged / CONFIG_NAME).is_file() or not has_full_weights(merged):
        return None
    return (
        merged if (merged / CONFIG_NAME).stat().st_mtime >= (folder / CONFIG_NAME).stat().st_mtime else None
    )


def checkpoint_weights(folder: Path, base: str | None = None) -> CheckpointWeights:
    """What loads the checkpoint `folder` (resolved: model/persistence/checkpoint_path.py).

    A folder with full weights is itself. A LoRA checkpoint (adapter only) is the run's merged model when the run
    wrote one after it (`merged_model_of`), else its adapter on `base`, by default the run's `init.checkpoint`.
    An explicit `base` always takes the adapter on that base.

    Raises:
        ValueError: an adapter-only checkpoint with neither a merged model nor a base (`base_of`).
    """
    folder = Path(folder)
    if has_full_weights(folder) or not is_lora_checkpoint(folder):
        return CheckpointWeights(folder, description=f"checkpoint {folder}")
    merged = None if base else merged_model_of(folder)
    if merged is not None:
        return CheckpointWeights(merged, description=f"the LoRA run's merged model {merged} (of {folder})")
    base = base_of(folder, base)
    return CheckpointWeights(folder, base, f"the LoRA adapter of {folder} on its base {base}")


def base_of(checkpoint: Path, override: str | None) -> str:
    """The base weights of a LoRA checkpoint: `override`, else `init.checkpoint` of its train_config.json.

    Raises:
        ValueError: neither is set (a LoRA run on randomly initialised weights has no base to rebuild).
    """
    if override:
        return override
    train_config = checkpoint / TRAIN_CONFIG_NAME
    init = (_read_json(train_config).get("init") or {}) if train_config.is_file() else {}
    if init.get("checkpoint"):
        return str(init["checkpoint"])
    raise ValueError(
        f"{checkpoint} is a LoRA checkpoint without base weights and {train_config.name} names no "
        "init.checkpoint: pass --base_checkpoint <folder or repo id> (the weights the run started from), or "
        "release the full folder training merges at the end (<output_dir>/merged, lora.merge_at_end)"
    )


def local_folder(path_or_repo_id: str | Path) -> Path:
    """A local folder as is; a Hub repo id downloaded (snapshot_download, honouring HF_ENDPOINT / offline)."""
    path = Path(path_or_repo_id)
    if path.is_dir():
        return path
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(str(path_or_repo_id)))


def base_format(folder: Path) -> str:
    """`openfly_agent` for our folders, `openvla` for OpenVLA / released OpenFly-Agent HF folders."""
    model_type = _read_json(folder / CONFIG_NAME).get("model_type")
    return BASE_OURS if model_type == MODEL_TYPE else BASE_OPENVLA


def load_lora_agent(checkpoint: str | Path, base: str | Path):
    """The agent of a LoRA checkpoint: base weights (ours or OpenVLA) + its adapter, LoRA attached, eval mode.

    Args:
        checkpoint: folder (or Hub repo id) with config.json, the tokenizer and `adapter/`.
        base: folder (or Hub repo id) with the weights the run started from.

    Raises:
        ValueError: the base's model sections differ from the checkpoint's (wrong base), with the differences.
    """
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch + transformers
    from openfly_agent.model.language.lora import load_lora_adapter  # lazy: torch
    from openfly_agent.model.persistence.openvla_loader import agent_from_openvla_checkpoint  # lazy: torch
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig  # lazy: torch + transformers

    checkpoint, base = local_folder(checkpoint), local_folder(base)
    config = OpenFlyAgentConfig.from_pretrained(str(checkpoint))
    tokenizer = load_tokenizer(checkpoint) if (checkpoint / "tokenizer_config.json").is_file() else None
    if base_format(base) == BASE_OURS:
        agent = OpenFlyAgent.from_pretrained(str(base), tokenizer=tokenizer)
        _check_same_sections(agent.config.agent, config.agent, base, checkpoint)
    else:
        agent, report = agent_from_openvla_checkpoint(base, config.model_config, tokenizer=tokenizer)
        logger.info("base weights from the OpenVLA folder %s: %s", base, report.summary())
    load_lora_adapter(agent, checkpoint)
    return agent.eval()


def _check_same_sections(base_sections: dict, own_sections: dict, base: Path, checkpoint: Path) -> None:
    differing = _diff(base_sections, own_sections)
    if differing:
        raise ValueError(
            f"base {base} does not match the LoRA checkpoint {checkpoint}: model sections differ at "
            f"{differing[:8]}; pass the weights the run started from as --base_checkpoint"
        )


def _diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    keys = sorted(set(a) | set(b))
    out = []
    for key in keys:
        left, right = a.get(key), b.get(key)
        if isinstance(left, dict) and isinstance(right, dict):
            out += _diff(left, right, f"{prefix}{key}.")
        elif left != right:
            out.append(f"{prefix}{key}: {left!r} vs {right!r}")
    return out

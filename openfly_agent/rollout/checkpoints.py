"""Checkpoints as agents: `load_agent` builds `OpenFlyAgent` from our checkpoint folder or training run (a LoRA
run's: its merged model when the run wrote one, else the adapter on its base), a released OpenVLA / OpenFly-Agent
folder (through the `openvla-compat-7b` model config: the `openvla_history` memory and the `openvla_bins` head) or a Hub id."""

from __future__ import annotations

import dataclasses
import json
import logging
from datetime import datetime, timezone
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.model.config import ModelConfig, openvla_compat_7b_config
from openfly_agent.model.language.tokenizer import load_tokenizer
from openfly_agent.model.persistence.checkpoint_path import check_navigation_stage, resolve_checkpoint_folder
from openfly_agent.model.persistence.lora_checkpoint import checkpoint_weights, load_lora_agent
from openfly_agent.utils.config import load_yaml_config

logger = logging.getLogger(__name__)


class CheckpointError(ValueError):
    """A checkpoint that cannot act (a grounding-stage checkpoint, an unknown model type); the message names
    the folder and what to pass instead."""


def resolve_device(device: str, info_device=None) -> str:
    """`auto` -> the launcher's device for this process (accelerate), else cuda when present, else cpu."""
    import torch

    if device != "auto":
        return device
    if info_device is not None:
        return str(info_device)
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_dtype(dtype: str, device: str):
    """`auto` -> bfloat16 on CUDA, float32 elsewhere."""
    import torch

    if dtype == "auto":
        return torch.bfloat16 if device.startswith("cuda") else torch.float32
    return getattr(torch, dtype)


def checkpoint_folder(checkpoint: str) -> Path:
    """The checkpoint's HF folder: a folder with config.json as is; a training run (`<run>`,
    `<run>/checkpoints` or the `last` pointer file) resolved to its newest checkpoint; otherwise a Hub id
    resolved through the local Hub cache (or a download when online). A grounding-stage checkpoint is refused
    (CheckpointError naming the navigation stage: it has no trained action head)."""
    try:
        folder = resolve_checkpoint_folder(checkpoint)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"--checkpoint {checkpoint!r}: {err}") from err
    if folder is not None:
        try:
            check_navigation_stage(folder)
        except ValueError as err:
            raise CheckpointError(f"--checkpoint {checkpoint!r}: {err}") from err
        return folder
    if checkpoint.startswith((".", "/")) or checkpoint.count("/") != 1:
        raise FileNotFoundError(
            f"--checkpoint {checkpoint!r}: no config.json there (nor a training run with checkpoints/last, "
            "nor a Hub id 'owner/name')"
        )
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(repo_id=checkpoint))


def checkpoint_fingerprint(checkpoint: str) -> dict:
    """What identifies the weights behind `checkpoint`: the resolved folder and its weight files' sizes and
    modification times (a training run folder keeps its name while its newest checkpoint changes)."""
    folder = checkpoint_folder(checkpoint)
    if checkpoint_kind(folder) == C.MODEL_TYPE:
        folder = checkpoint_weights(folder).folder  # a LoRA run: its merged model, or the adapter checkpoint
    files = sorted([*folder.glob("*.safetensors"), *folder.glob(f"{C.ADAPTER_DIR_NAME}/*.safetensors")])
    return {
        "folder": str(folder.resolve()),
        "weights": {str(f.relative_to(folder)): [f.stat().st_size, f.stat().st_mtime_ns] for f in files},
    }


def describe_fingerprint(fingerprint: dict) -> str:
    """`<folder> (model.safetensors 7,779,564 B modified 2026-11-27 09:23:45 UTC)`."""
    files = [
        f"{name} {_describe_file(entry)}" for name, entry in sorted(fingerprint.get("weights", {}).items())
    ]
    return f"{fingerprint.get('folder')} ({', '.join(files) or 'no weight files'})"


def describe_weights_change(recorded: dict, current: dict) -> str:
    """What differs between two `checkpoint_fingerprint`s, in words: `<folder A> (...) -> <folder B> (...)` for
    other folders, else `<folder>: ` and its `weight_file_changes`."""
    if recorded.get("folder") != current.get("folder"):
        return f"{describe_fingerprint(recorded)} -> {describe_fingerprint(current)}"
    return f"{current.get('folder')}: {weight_file_changes(recorded, current)}"


def weight_file_changes(recorded: dict, current: dict) -> str:
    """Which weight files of two fingerprints of one folder changed and when: `model.safetensors was written
    again: 7,779,564 B modified 2026-11-27 09:14:56 UTC then, 7,779,564 B modified 2026-11-27 10:02:11 UTC now`."""
    before, after = recorded.get("weights") or {}, current.get("weights") or {}
    changes = []
    for name in sorted(set(before) | set(after)):
        if name not in after:
            changes.append(f"{name} is gone (it was {_describe_file(before[name])})")
        elif name not in before:
            changes.append(f"{name} is new ({_describe_file(after[name])})")
        elif list(before[name]) != list(after[name]):
            then, now = _describe_file(before[name]), _describe_file(after[name])
            if then == now:  # within the same second: show the milliseconds
                then, now = _describe_file(before[name], "%S.%f"), _describe_file(after[name], "%S.%f")
            changes.append(f"{name} was written again: {then} then, {now} now")
    return "; ".join(changes) or "no weight file changed"


def _describe_file(entry: list, seconds: str = "%S") -> str:
    """`7,779,564 B modified 2026-11-27 09:23:45 UTC` from a fingerprint's [size, mtime_ns]."""
    size, mtime_ns = entry
    when = datetime.fromtimestamp(mtime_ns / 1e9, tz=timezone.utc).strftime(f"%Y-%m-%d %H:%M:{seconds}")
    return f"{size:,} B modified {when[:23] if seconds != '%S' else when} UTC"


def checkpoint_kind(folder: Path) -> str:
    """`openfly_agent` (ours) or `openvla` (a released OpenVLA / OpenFly-Agent folder), from config.json."""
    config = folder / C.CONFIG_NAME
    if not config.is_file():
        raise FileNotFoundError(f"{config} not found: a checkpoint folder holds config.json and safetensors")
    model_type = json.loads(config.read_text()).get("model_type")
    if model_type == C.MODEL_TYPE:
        return C.MODEL_TYPE
    if model_type == "openvla":
        return "openvla"
    raise CheckpointError(f"{config}: model_type {model_type!r} is neither {C.MODEL_TYPE!r} nor 'openvla'")


def _released_model_config(model_config: str | None, decode_rule: str | None, unnorm_key: str | None):
    cfg = load_yaml_config(ModelConfig, model_config) if model_config else openvla_compat_7b_config()
    head = dataclasses.replace(
        cfg.action_head,
        unnorm_key=unnorm_key or cfg.action_head.unnorm_key,
        decode_rule=decode_rule or cfg.action_head.decode_rule,
    )
    return dataclasses.replace(cfg, action_head=head)


def load_agent(
    checkpoint: str,
    device: str = "cpu",
    dtype: str = "auto",
    decode_rule: str | None = None,
    unnorm_key: str | None = None,
    model_config: str | None = None,
):
    """Load the agent of `checkpoint` on `device`, in eval mode, with the decoding settings applied.

    `checkpoint`: a checkpoint folder, a training run (its newest checkpoint) or a Hub id (`checkpoint_folder`);
    `dtype`: auto (float32 on CPU, bfloat16 on CUDA) | float32 | bfloat16 | float16; `decode_rule`,
    `unnorm_key`: the `openvla_bins` decoding (None keeps the checkpoint's); `model_config`: the ModelConfig YAML
    of a released (OpenVLA-format) folder (None: the 7B compat preset).

    Our folders load with `OpenFlyAgent.from_pretrained`, then take the decoding settings through their config
    (`set_action_decoding`: the action tokenizer, `config.action_tokenizer` and the processor all follow);
    OpenVLA-format folders (the released OpenFly-Agent) through `agent_from_openvla_checkpoint` with the
    released model's config (`model_config`, default the `openvla-compat-7b` preset) and its `openvla_bins` head.
    A LoRA checkpoint (adapter only) loads as `checkpoint_weights` says, logged: the run's merged model when it
    wrote one, else the adapter on its base (the run's `init.checkpoint`).
    """
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch + transformers
    from openfly_agent.model.persistence.openvla_loader import (  # lazy: torch
        CheckpointMismatchError,
        agent_from_openvla_checkpoint,
    )

    folder = checkpoint_folder(checkpoint)
    torch_dtype = resolve_dtype(dtype, device)
    if checkpoint_kind(folder) == "openvla":
        try:
            agent, report = agent_from_openvla_checkpoint(
                folder,
                _released_model_config(model_config, decode_rule, unnorm_key),
                tokenizer=load_tokenizer(folder),
                device=device,
                dtype=torch_dtype,
            )
        except CheckpointMismatchError as err:
            raise CheckpointError(
                f"{err} (the ModelConfig YAML of a released folder: eval.py --agent.model_config=<file>; "
                f"now {model_config or 'the 7B openvla_compat preset'})"
            ) from err
        logger.info("released checkpoint %s: %s", folder, report.summary())
        return agent.eval()
    weights = checkpoint_weights(folder)
    if weights.base is None:
        agent = OpenFlyAgent.from_pretrained(str(weights.folder), dtype=torch_dtype)
    else:
        agent = load_lora_agent(weights.folder, weights.base).to(torch_dtype)
    agent = agent.to(device).eval()
    agent.set_action_decoding(decode_rule=decode_rule, unnorm_key=unnorm_key)
    logger.info("loaded %s on %s (%s)", weights.description, device, torch_dtype)
    return agent

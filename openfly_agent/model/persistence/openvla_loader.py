"""Load `openvla/openvla-7b` / `IPEC-COMMUNITY/openfly-agent-7b` safetensors into an `OpenFlyAgent` by name.

Every checkpoint key is accounted for: loaded into the agent, or one of the keys of the ViT parts the
agent prunes (the last block, the final norm, SigLIP's attention-pool head; OpenVLA never uses them).
Agent keys missing from the checkpoint may only belong to the new modules (`grounding_head.*`). Anything
else (unexpected, missing or wrong shape) raises, naming the keys. LayerScale is `ls1.scale_factor` in
OpenVLA files and `ls1.gamma` in timm (and here); both directions are mapped.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from openfly_agent.model.persistence.checkpoint_path import open_safetensors
from openfly_agent.model.vision.backbone import build_featurizers

logger = logging.getLogger(__name__)

NEW_MODULE_PREFIXES = ("grounding_head.", "box_token_embed.")
VISION_PREFIXES = ("vision_backbone.featurizer.", "vision_backbone.fused_featurizer.")
_OPENVLA_SCALE = re.compile(r"\.(ls[12])\.scale_factor$")
_TIMM_SCALE = re.compile(r"\.(ls[12])\.gamma$")


@dataclass
class LoadReport:
    """What `load_openvla_weights` did with every key."""

    loaded: list[str] = field(default_factory=list)  # agent keys filled from the checkpoint
    missing_new: list[str] = field(default_factory=list)  # agent keys of new modules (kept as initialised)
    unused: list[str] = field(default_factory=list)  # checkpoint keys of the pruned ViT parts

    def summary(self) -> str:
        """One line for logs."""
        return f"loaded {len(self.loaded)} tensors, {len(self.missing_new)} new, {len(self.unused)} unused"


def openvla_to_agent_key(key: str) -> str:
    """`...ls1.scale_factor` (OpenVLA HF files) -> `...ls1.gamma` (timm); other keys unchanged."""
    return _OPENVLA_SCALE.sub(r".\1.gamma", key)


def agent_to_openvla_key(key: str) -> str:
    """`...ls1.gamma` -> `...ls1.scale_factor`; other keys unchanged."""
    return _TIMM_SCALE.sub(r".\1.scale_factor", key)


def to_openvla_state_dict(agent: nn.Module) -> dict[str, torch.Tensor]:
    """The agent's weights in the OpenVLA key layout, without the new modules (for export / comparison)."""
    return {
        agent_to_openvla_key(name): tensor
        for name, tensor in agent.state_dict().items()
        if not name.startswith(NEW_MODULE_PREFIXES)
    }


def pruned_vision_keys(agent: nn.Module) -> set[str]:
    """Agent-style keys the full timm ViTs have and the agent's pruned ones do not."""
    with torch.device("meta"):
        full = build_featurizers(agent.model_cfg.vision, prune=False)
    ours = (agent.vision_backbone.featurizer, agent.vision_backbone.fused_featurizer)
    keys = set()
    for prefix, whole, pruned in zip(VISION_PREFIXES, full, ours):
        keys |= {prefix + k for k in set(whole.state_dict()) - set(pruned.state_dict())}
    return keys


def _iter_checkpoint(source) -> Iterator[tuple[str, torch.Tensor]]:
    if isinstance(source, dict):
        yield from source.items()
        return
    path = Path(source)
    if path.is_dir():
        index = path / "model.safetensors.index.json"
        if index.is_file():
            files = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        else:
            files = sorted(p.name for p in path.glob("*.safetensors"))
        paths = [path / name for name in files]
    else:
        paths = [path]
    if not paths or not all(p.is_file() for p in paths):
        raise FileNotFoundError(f"no safetensors weights found at {path}")
    for file in paths:
        with open_safetensors(file) as handle:  # a truncated file: UnreadableWeightsError naming it
            for key in handle.keys():  # noqa: SIM118 (safe_open is not a mapping)
                yield key, handle.get_tensor(key)


def load_openvla_weights(agent: nn.Module, path_or_state_dict) -> LoadReport:
    """Copy OpenVLA-layout weights into `agent` in place, accounting for every key.

    Args:
        agent: an `OpenFlyAgent` whose architecture matches the checkpoint (e.g. the 7B presets).
        path_or_state_dict: a safetensors file, a folder (sharded with an index, or `*.safetensors`), or
            a state dict.

    Returns:
        A `LoadReport`.

    Raises:
        ValueError: listing unexpected, missing (other than new-module) and wrong-shape keys.
    """
    if getattr(agent.language_model, "peft_config", None) is not None:
        raise ValueError("load OpenVLA weights before attaching LoRA")
    targets = agent.state_dict()
    prunable = pruned_vision_keys(agent)
    report, unexpected, wrong_shape = LoadReport(), [], []
    for key, tensor in _iter_checkpoint(path_or_state_dict):
        name = openvla_to_agent_key(key)
        if name in targets:
            if tuple(tensor.shape) != tuple(targets[name].shape):
                wrong_shape.append(
                    f"{key}: checkpoint {tuple(tensor.shape)} vs agent {tuple(targets[name].shape)}"
                )
                continue
            with torch.no_grad():
                targets[name].copy_(tensor.to(targets[name].dtype))
            report.loaded.append(name)
        elif name in prunable:
            report.unused.append(key)
        else:
            unexpected.append(key)
    missing = sorted(set(targets) - set(report.loaded))
    report.missing_new = [k for k in missing if k.startswith(NEW_MODULE_PREFIXES)]
    missing_old = [k for k in missing if not k.startswith(NEW_MODULE_PREFIXES)]
    problems = []
    for title, keys in (("unexpected", unexpected), ("missing", missing_old), ("wrong shape", wrong_shape)):
        if keys:
            problems.append(f"{len(keys)} {title} key(s): {keys[:20]}{' ...' if len(keys) > 20 else ''}")
    if problems:
        source = path_or_state_dict if not isinstance(path_or_state_dict, dict) else "state dict"
        raise ValueError(f"OpenVLA checkpoint {source} does not match the agent: " + "; ".join(problems))
    logger.info("OpenVLA weights: %s", report.summary())
    return report


def read_openvla_norm_stats(folder: str | Path) -> dict:
    """`norm_stats` of an OpenVLA / OpenFly HF folder's config.json (`{}` when absent)."""
    config = Path(folder) / "config.json"
    if not config.is_file():
        raise FileNotFoundError(f"{config} not found (an OpenVLA HF folder holds config.json)")
    return json.loads(config.read_text()).get("norm_stats") or {}


def agent_from_openvla_checkpoint(folder: str | Path, cfg, tokenizer=None, device="cpu", dtype=None):
    """Build an agent for `cfg` without a random init, fill it from an OpenVLA HF folder, init new modules.

    The agent is created on the meta device and materialised once on `device` in `dtype`, so a 7B
    checkpoint costs one copy of the weights. Norm stats come from the folder's config.json.

    Returns:
        (agent, LoadReport).
    """
    from openfly_agent.model.agent import (
        OpenFlyAgent,  # lazy: transformers; the state-dict conversions need torch only
    )

    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(
            cfg, tokenizer=tokenizer, norm_stats=read_openvla_norm_stats(folder)
        )
    agent.to_empty(device=device)
    if dtype is not None:
        agent.to(dtype)
    report = load_openvla_weights(agent, folder)
    with torch.no_grad():
        for module in agent.modules():  # new modules and non-persistent buffers (rotary inv_freq)
            if type(module).__name__.endswith("RotaryEmbedding"):
                unwrap = agent.language_model
                unwrap._init_weights(module)
        for new_module in (agent.grounding_head, agent.box_token_embed):  # NEW_MODULE_PREFIXES
            if new_module is not None:
                for module in new_module.modules():
                    agent._init_weights(module)
    return agent.eval(), report

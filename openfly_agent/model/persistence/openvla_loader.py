"""Load `openvla/openvla-7b` / `IPEC-COMMUNITY/openfly-agent-7b` safetensors into an `OpenFlyAgent` by name.

Every checkpoint key is accounted for: loaded into the agent, or one of the keys of the ViT parts the
agent prunes (the last block, the final norm, SigLIP's attention-pool head; OpenVLA never uses them).
Agent keys missing from the checkpoint may only belong to the new modules (`grounding_head.*`). Anything
else (unexpected, missing or wrong shape) raises one line: the model sizes that differ (LLM width, ViT width, ...)
and a few keys of each kind with their shapes (`mismatch_message`); a folder is checked from its headers before
any weight is allocated. LayerScale is `ls1.scale_factor` in
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
        for name, tensor in agent.network.state_dict().items()
        if not name.startswith(NEW_MODULE_PREFIXES)
    }


def pruned_vision_keys(agent: nn.Module) -> set[str]:
    """Agent-style keys the full timm ViTs have and the agent's pruned ones do not."""
    with torch.device("meta"):
        full = build_featurizers(agent.model_cfg.vision, prune=False)
    ours = (agent.network.vision_backbone.featurizer, agent.network.vision_backbone.fused_featurizer)
    keys = set()
    for prefix, whole, pruned in zip(VISION_PREFIXES, full, ours):
        keys |= {prefix + k for k in set(whole.state_dict()) - set(pruned.state_dict())}
    return keys


# Named sizes of the model, read off one tensor each: (name, agent key, dimension); a mismatch names these first.
DIMENSIONS = (
    ("llm hidden size", "language_model.model.embed_tokens.weight", 1),
    ("llm vocabulary", "language_model.model.embed_tokens.weight", 0),
    ("vision width", "vision_backbone.featurizer.patch_embed.proj.weight", 0),
    ("fused vision width", "vision_backbone.fused_featurizer.patch_embed.proj.weight", 0),
    ("vision patch size", "vision_backbone.featurizer.patch_embed.proj.weight", 2),
    ("vision positions", "vision_backbone.featurizer.pos_embed", 1),
    ("projector width", "projector.fc1.weight", 0),
)
# Repeated blocks, counted by index: (name, key prefix before the index).
DEPTHS = (
    ("llm layers", "language_model.model.layers."),
    ("vision blocks", "vision_backbone.featurizer.blocks."),
)
REDUCED_WIDTH_HINT = "did you forget --model=configs/model/reduced-width.yaml?"


class CheckpointMismatchError(ValueError):
    """An OpenVLA-layout checkpoint whose tensors do not fit the configured model (one line, `mismatch_message`)."""


def _checkpoint_files(path: Path) -> list[Path]:
    """The safetensors files of a file or folder (sharded with an index, or `*.safetensors`)."""
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
    return paths


def _iter_checkpoint(source) -> Iterator[tuple[str, torch.Tensor]]:
    if isinstance(source, dict):
        yield from source.items()
        return
    for file in _checkpoint_files(Path(source)):
        with open_safetensors(file) as handle:  # a truncated file: UnreadableWeightsError naming it
            for key in handle.keys():  # noqa: SIM118 (safe_open is not a mapping)
                yield key, handle.get_tensor(key)


def checkpoint_shapes(path: str | Path) -> dict[str, tuple[int, ...]]:
    """{checkpoint key: shape} from the safetensors headers alone (no tensor is read)."""
    shapes = {}
    for file in _checkpoint_files(Path(path)):
        with open_safetensors(file) as handle:
            for key in handle.keys():  # noqa: SIM118 (safe_open is not a mapping)
                shapes[key] = tuple(handle.get_slice(key).get_shape())
    return shapes


def _named_sizes(shapes: dict[str, tuple[int, ...]]) -> dict[str, int]:
    """The DIMENSIONS and DEPTHS of a model from its agent-style {key: shape}."""
    sizes = {}
    for name, key, dim in DIMENSIONS:
        if key in shapes and len(shapes[key]) > dim:
            sizes[name] = shapes[key][dim]
    for name, prefix in DEPTHS:
        indices = {k[len(prefix) :].split(".", 1)[0] for k in shapes if k.startswith(prefix)}
        if indices:
            sizes[name] = len(indices)
    return sizes


def mismatch_message(
    source,
    found: dict[str, tuple[int, ...]],
    expected: dict[str, tuple[int, ...]],
    unexpected: list[str],
    missing: list[str],
) -> str:
    """One line on a checkpoint that does not fit the configured model: the named sizes that differ
    ("checkpoint llm hidden size 128, config 4096"), then how many keys are unexpected, missing or of another
    shape, with a few of each (shapes given). `found` / `expected`: agent-style {key: shape} of each side (the
    checkpoint's without the ViT parts the agent prunes)."""
    have, want = _named_sizes(found), _named_sizes(expected)
    sizes = [
        f"checkpoint {name} {have[name]}, config {want[name]}"
        for name in want
        if have.get(name, want[name]) != want[name]
    ]
    wrong = [k for k in found if k in expected and tuple(found[k]) != tuple(expected[k])]
    parts = ["; ".join(sizes)] if sizes else []
    if wrong:
        shown = [f"{k} {tuple(found[k])} vs {tuple(expected[k])}" for k in wrong]
        parts.append(_some(shown, "tensor", "of another shape (checkpoint vs config)"))
    for title, keys in (("unexpected", unexpected), ("missing", missing)):
        if keys:
            parts.append(_some(keys, f"{title} key"))
    hint = "use the model config the checkpoint was made for"
    if have.get("llm hidden size", 0) < want.get("llm hidden size", 0):
        hint = REDUCED_WIDTH_HINT + " (or " + hint + ")"
    return f"OpenVLA checkpoint {source} does not match the model config: {'; '.join(parts)}; {hint}"


def _some(items: list[str], noun: str, after: str = "", shown: int = 3) -> str:
    """`25 tensors of another shape, e.g. a, b, c` / `1 missing key: a`."""
    head = f"{len(items)} {noun}{'s' if len(items) != 1 else ''}{' ' + after if after else ''}"
    return f"{head}{', e.g. ' if len(items) > shown else ': '}{', '.join(items[:shown])}"


def check_openvla_shapes(agent: nn.Module, folder: str | Path) -> None:
    """Compare an OpenVLA folder's tensor shapes (headers only) with `agent`'s (which may be on the meta device)
    before any weight is read or allocated.

    Raises:
        CheckpointMismatchError: one line, `mismatch_message`.
    """
    targets = {name: tuple(t.shape) for name, t in agent.network.state_dict().items()}
    prunable = pruned_vision_keys(agent)
    found = {openvla_to_agent_key(k): shape for k, shape in checkpoint_shapes(folder).items()}
    found = {k: shape for k, shape in found.items() if k not in prunable}  # the ViT parts the agent drops
    unexpected = sorted(k for k in found if k not in targets and k not in prunable)
    missing = sorted(k for k in targets if k not in found and not k.startswith(NEW_MODULE_PREFIXES))
    wrong = any(k in targets and shape != targets[k] for k, shape in found.items())
    if unexpected or missing or wrong:
        raise CheckpointMismatchError(mismatch_message(folder, found, targets, unexpected, missing))


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
    if getattr(agent.network.language_model, "peft_config", None) is not None:
        raise ValueError("load OpenVLA weights before attaching LoRA")
    targets = agent.network.state_dict()
    prunable = pruned_vision_keys(agent)
    report, unexpected, found = LoadReport(), [], {}
    for key, tensor in _iter_checkpoint(path_or_state_dict):
        name = openvla_to_agent_key(key)
        if name not in prunable:
            found[name] = tuple(tensor.shape)
        if name in targets:
            if tuple(tensor.shape) != tuple(targets[name].shape):
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
    missing_old = [k for k in missing if not k.startswith(NEW_MODULE_PREFIXES) and k not in found]
    expected = {name: tuple(t.shape) for name, t in targets.items()}
    wrong_shape = any(name in expected and shape != expected[name] for name, shape in found.items())
    if unexpected or missing_old or wrong_shape:
        source = path_or_state_dict if not isinstance(path_or_state_dict, dict) else "state dict"
        raise CheckpointMismatchError(mismatch_message(source, found, expected, unexpected, missing_old))
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
    check_openvla_shapes(agent, folder)  # from the headers: a mismatch fails before 7B weights are allocated
    agent.to_empty(device=device)
    if dtype is not None:
        agent.to(dtype)
    report = load_openvla_weights(agent, folder)
    with torch.no_grad():
        for module in agent.modules():  # new modules and non-persistent buffers (rotary inv_freq)
            if type(module).__name__.endswith("RotaryEmbedding"):
                unwrap = agent.network.language_model
                unwrap._init_weights(module)
        # NEW_MODULE_PREFIXES
        for new_module in (agent.network.grounding_head, agent.network.box_token_embed):
            if new_module is not None:
                for module in new_module.modules():
                    agent._init_weights(module)
    return agent.eval(), report

"""Fold LoRA adapters into their base weights from an in-memory state dict (CPU, no second base model)."""

from __future__ import annotations

import logging
import re

import torch
from torch import nn

logger = logging.getLogger(__name__)

_LORA_A = re.compile(r"^(?P<prefix>.*)\.lora_A\.(?P<adapter>[^.]+)\.weight$")
_UNSUPPORTED = ("lora_embedding_A", "lora_magnitude_vector", "modules_to_save")


def lora_scalings(model: nn.Module, adapter: str = "default") -> dict[str, float]:
    """The scaling (alpha / r, or alpha / sqrt(r) with rsLoRA) of every LoRA layer, keyed by module name.

    Read from the live peft layers, so rank and alpha patterns are honoured without parsing the peft config.
    """
    scalings = {}
    for name, module in model.named_modules():
        scaling = getattr(module, "scaling", None)
        if isinstance(scaling, dict) and adapter in scaling and hasattr(module, "lora_A"):
            scalings[name] = float(scaling[adapter])
    return scalings


def strip_peft_prefixes(key: str) -> str:
    """`a.base_model.model.b.base_layer.weight` -> `a.b.weight`: the key the plain model uses."""
    key = key.removeprefix("base_model.model.").replace(".base_model.model.", ".")
    return key.replace(".base_layer.", ".")


def merge_lora_state_dict(
    state_dict: dict[str, torch.Tensor], scalings: dict[str, float], adapter: str = "default"
) -> dict[str, torch.Tensor]:
    """Return the plain-model state dict with every LoRA pair folded in: `W + scaling * (B @ A)`.

    The maths runs in float32 on the CPU and the result takes the base weight's dtype; the input is unchanged.

    Args:
        state_dict: full state dict of the peft-wrapped model (e.g. `accelerator.get_state_dict(model)`).
        scalings: `lora_scalings(model)`; keys are module names as in `state_dict` (before prefix stripping).
        adapter: peft adapter name.

    Raises:
        ValueError: an adapter kind this merge does not handle (embedding LoRA, DoRA, modules_to_save), or a
            LoRA pair without its base weight or scaling.
    """
    unsupported = sorted({k for k in state_dict for marker in _UNSUPPORTED if f".{marker}." in k})
    if unsupported:
        raise ValueError(
            f"cannot merge these adapter tensors (only Linear LoRA is supported): {unsupported[:5]}"
        )
    merged: dict[str, torch.Tensor] = {}
    lora_keys: set[str] = set()
    for key, tensor_a in state_dict.items():
        match = _LORA_A.match(key)
        if match is None or match.group("adapter") != adapter:
            continue
        prefix = match.group("prefix")
        key_b, key_base = f"{prefix}.lora_B.{adapter}.weight", f"{prefix}.base_layer.weight"
        if key_b not in state_dict or key_base not in state_dict or prefix not in scalings:
            raise ValueError(f"LoRA layer {prefix!r} lacks lora_B, its base weight or its scaling")
        base = state_dict[key_base]
        # (out, r) @ (r, in) -> (out, in)
        delta = state_dict[key_b].detach().cpu().float() @ tensor_a.detach().cpu().float()
        merged[strip_peft_prefixes(key_base)] = (base.detach().cpu().float() + scalings[prefix] * delta).to(
            base.dtype
        )
        lora_keys.update({key, key_b, key_base})
    for key, tensor in state_dict.items():
        if key in lora_keys or ".lora_" in key:
            continue
        merged.setdefault(strip_peft_prefixes(key), tensor.detach().cpu())
    logger.info("merged %d LoRA layers into their base weights", len(lora_keys) // 3)
    return merged

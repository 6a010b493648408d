"""Level-1 model: vision, projector, LLM, grounding, keyframes, merging, memory, actions, agent.

The torch / transformers parts are imported on first use, so `import openfly_agent.model` stays cheap.
"""

from __future__ import annotations

import importlib

from .config import ModelConfig, make_model_config, openfly_7b_config, tiny_config

_LAZY = {
    "OpenFlyAgent": ".agent",
    "register_auto_classes": ".agent",
    "OpenFlyAgentConfig": ".pretrained_config",
    "OpenFlyProcessor": ".processor",
    "ImageTransform": ".image_transform",
    "ActionTokenizer": ".action_tokenizer",
    "KeyframeSelector": ".keyframes",
    "MemoryBank": ".memory",
    "grid_pool": ".memory",
    "merge_into_reference": ".merging",
    "train_bpe_tokenizer": ".tokenizer",
    "load_tokenizer": ".tokenizer",
    "attach_lora": ".lora",
    "merge_lora": ".lora",
    "save_lora_adapter": ".lora",
    "load_lora_adapter": ".lora",
    "load_openvla_weights": ".openvla_loader",
    "agent_from_openvla_checkpoint": ".openvla_loader",
}

__all__ = ["ModelConfig", "make_model_config", "openfly_7b_config", "tiny_config", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

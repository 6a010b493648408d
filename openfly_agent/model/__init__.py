"""Level-1 model: the agent (agent.py: loss, processor, save / load) around its network (network.py: encode,
decode), the closed-loop session (session.py) and the components by sub-package: vision/, grounding/, memory/,
language/, persistence/ (checkpoint folders).

The torch / transformers parts are imported on first use, so `import openfly_agent.model` stays cheap.
"""

from __future__ import annotations

import importlib

from openfly_agent.model.config import ModelConfig, make_model_config, openfly_7b_config, tiny_config

_LAZY = {
    "OpenFlyAgent": ".agent",
    "register_auto_classes": ".agent",
    "OpenFlyNetwork": ".network",
    "AgentSession": ".session",
    "StepResult": ".episode",
    "OpenFlyAgentConfig": ".pretrained_config",
    "OpenFlyProcessor": ".processor",
    "ImageTransform": ".vision.image_transform",
    "ActionTokenizer": ".language.action_tokenizer",
    "KeyframeSelector": ".memory.keyframes",
    "MemoryBank": ".memory.bank",
    "grid_pool": ".memory.bank",
    "merge_into_reference": ".memory.merging",
    "train_bpe_tokenizer": ".language.tokenizer",
    "load_tokenizer": ".language.tokenizer",
    "attach_lora": ".language.lora",
    "merge_lora": ".language.lora",
    "save_lora_adapter": ".language.lora",
    "load_lora_adapter": ".language.lora",
    "load_openvla_weights": ".persistence.openvla_loader",
    "agent_from_openvla_checkpoint": ".persistence.openvla_loader",
}

__all__ = ["ModelConfig", "make_model_config", "openfly_7b_config", "tiny_config", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

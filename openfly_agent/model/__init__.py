"""Level-1 model: the agent (agent.py: loss, processor, save / load) around its network (network.py: encode,
decode), the closed-loop session (session.py) and the components by sub-package: vision/, grounding/, memory/,
language/, persistence/ (checkpoint folders).

The public API: the agent, its session and network, the configs, the processor, the tokenizer and the loaders
(`from openfly_agent.model import OpenFlyAgent`); the torch / transformers parts are imported on first use, so
`import openfly_agent.model` stays cheap.
"""

from __future__ import annotations

import importlib

from openfly_agent.model.config import ModelConfig, make_model_config, openfly_7b_config, tiny_config

_LAZY = {
    "OpenFlyAgent": ".agent",
    "register_auto_classes": ".agent",
    "AgentSession": ".session",
    "StepResult": ".episode",
    "OpenFlyNetwork": ".network",
    "OpenFlyAgentConfig": ".pretrained_config",
    "OpenFlyProcessor": ".processor",
    "load_tokenizer": ".language.tokenizer",
    "train_bpe_tokenizer": ".language.tokenizer",
    "attach_lora": ".language.lora",
    "merge_lora": ".language.lora",
    "save_lora_adapter": ".language.lora",
    "load_lora_adapter": ".language.lora",
    "load_lora_agent": ".persistence.lora_checkpoint",
    "load_openvla_weights": ".persistence.openvla_loader",
    "agent_from_openvla_checkpoint": ".persistence.openvla_loader",
}

__all__ = ["ModelConfig", "make_model_config", "openfly_7b_config", "tiny_config", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""In-process Auto-class registration: `AutoModel.from_pretrained(folder)` without trust_remote_code."""

from __future__ import annotations

from openfly_agent.constants import MODEL_TYPE


def register_auto_classes() -> None:
    """Register `OpenFlyAgentConfig` with AutoConfig and `OpenFlyAgent` with AutoModel (idempotent).

    Called explicitly (never at import time). Without it, released folders still load anywhere through
    `trust_remote_code=True` and the `auto_map` their config.json carries.
    """
    from transformers import AutoConfig, AutoModel

    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.configuration import OpenFlyAgentConfig

    AutoConfig.register(MODEL_TYPE, OpenFlyAgentConfig, exist_ok=True)
    AutoModel.register(OpenFlyAgentConfig, OpenFlyAgent, exist_ok=True)

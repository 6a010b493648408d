"""`OpenFlyAgentConfig`: the transformers config of the agent, wrapping the typed `ModelConfig`.

config.json holds the model sections under `agent`, the norm stats (OpenVLA `dataset_statistics` profiles,
may be empty) and the action tokenizer settings, so a checkpoint folder rebuilds itself.
"""

from __future__ import annotations

from huggingface_hub.dataclasses import strict
from transformers import PreTrainedConfig

from openfly_agent.constants import MODEL_TYPE
from openfly_agent.model.config import (
    LLM_TINY,
    TINY_LLM,
    TINY_VISION,
    VISION_TINY,
    ModelConfig,
)
from openfly_agent.utils.config import config_from_dict, config_to_dict

# Before the tiny-only size fields defaulted to None, every config.json held the tiny sizes, also under the
# 7B presets (which ignored them). Those exact values are dropped when such a file is read.
_LEGACY_TINY_SIZES = (("vision", VISION_TINY, TINY_VISION), ("llm", LLM_TINY, TINY_LLM))


@strict
class OpenFlyAgentConfig(PreTrainedConfig):
    """Transformers config of `OpenFlyAgent` (`model_type = "openfly_agent"`).

    Args:
        agent: `ModelConfig` as a dict (`config_to_dict`); None gives the default (tiny) sections.
        norm_stats: dataset statistics profiles, `{key: {"action": {q01, q99, ...}, ...}}`.
        action_tokenizer: `ActionTokenizer.to_dict()` of the agent (informational; rebuilt from `agent`).
    """

    model_type = MODEL_TYPE

    agent: dict | None = None
    norm_stats: dict | None = None
    action_tokenizer: dict | None = None

    def __post_init__(self, **kwargs):
        # Round trip through the dataclass: validates every section and fills defaults of older files.
        self.agent = config_to_dict(
            config_from_dict(ModelConfig, _without_legacy_tiny_sizes(self.agent or {}))
        )
        self.norm_stats = dict(self.norm_stats or {})
        super().__post_init__(**kwargs)

    @property
    def model_config(self) -> ModelConfig:
        """The typed model sections."""
        return config_from_dict(ModelConfig, self.agent)

    @classmethod
    def from_model_config(
        cls, cfg: ModelConfig, norm_stats: dict | None = None, action_tokenizer: dict | None = None
    ) -> OpenFlyAgentConfig:
        """Wrap a `ModelConfig` (and optional norm stats) into a transformers config."""
        return cls(agent=config_to_dict(cfg), norm_stats=norm_stats or {}, action_tokenizer=action_tokenizer)


def _without_legacy_tiny_sizes(agent: dict) -> dict:
    """`agent` without the tiny sizes an older file holds in a non-tiny section (only values equal to them)."""
    agent = dict(agent)
    for section, tiny_preset, sizes in _LEGACY_TINY_SIZES:
        values = agent.get(section)
        if isinstance(values, dict) and values.get("preset", tiny_preset) != tiny_preset:
            agent[section] = {k: v for k, v in values.items() if not (k in sizes and v == sizes[k])}
    return agent

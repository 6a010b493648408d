"""`OpenFlyAgentConfig`: the transformers config of the agent, wrapping the typed `ModelConfig`.

config.json holds the model sections under `agent`, the norm stats (OpenVLA `dataset_statistics` profiles,
may be empty) and the action tokenizer settings, so a checkpoint folder rebuilds itself.
"""

from __future__ import annotations

from huggingface_hub.dataclasses import strict
from transformers import PreTrainedConfig

from openfly_agent.constants import MODEL_TYPE
from openfly_agent.model.config import ModelConfig
from openfly_agent.model.config_upgrade import upgraded_model_dict
from openfly_agent.utils.config import config_from_dict, config_to_dict


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
        # Round trip through the dataclass: validates every section, upgrades and fills defaults of older files.
        self.agent = config_to_dict(config_from_dict(ModelConfig, upgraded_model_dict(self.agent or {})))
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

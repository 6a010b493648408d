"""LoRA on the agent's LLM through peft: attach, save / load the adapter, merge (merge_and_unload).

The adapter folder holds peft's files for the LLM plus `trainables.safetensors` with the projector and the
grounding head, which the `lora` freeze stage also trains.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from torch import nn

from openfly_agent.constants import ADAPTER_DIR_NAME
from openfly_agent.model.config import LoraSettings
from openfly_agent.model.freeze import STAGE_LORA, freeze

logger = logging.getLogger(__name__)
# peft (0.21) reads transformers 5's deprecated `is_gradient_checkpointing` when it wraps a model: a FutureWarning
# on every LoRA run that is no call of ours and that nothing here can act on
PEFT_CHECKPOINTING_WARNING = "`is_gradient_checkpointing` is deprecated"

TRAINABLES_NAME = "trainables.safetensors"
TRAINABLE_PARTS = ("projector", "grounding_head")


@contextmanager
def _without_peft_checkpointing_warning() -> Iterator[None]:
    """peft wrapping a model, without its FutureWarning about transformers' `is_gradient_checkpointing`."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=PEFT_CHECKPOINTING_WARNING, category=FutureWarning)
        yield


def has_lora(agent: nn.Module) -> bool:
    """Whether peft adapters are attached to the agent's LLM."""
    return getattr(agent.network.language_model, "peft_config", None) is not None


def attach_lora(agent: nn.Module, settings: LoraSettings | None = None) -> nn.Module:
    """Wrap the LLM with fresh LoRA adapters and apply the `lora` freeze stage; returns the agent."""
    from peft import LoraConfig, get_peft_model

    if has_lora(agent):
        raise ValueError("LoRA is already attached to this agent")
    settings = settings or LoraSettings()
    targets = settings.target_modules
    config = LoraConfig(
        r=settings.rank,
        lora_alpha=settings.alpha,
        lora_dropout=settings.dropout,
        target_modules=targets if targets == "all-linear" else [t.strip() for t in targets.split(",")],
        init_lora_weights=True if settings.init == "default" else settings.init,
        bias="none",
    )
    with _without_peft_checkpointing_warning():
        agent.network.language_model = get_peft_model(agent.network.language_model, config)
    freeze(agent, STAGE_LORA)
    return agent


def _trainables_state(agent: nn.Module) -> dict:
    return {
        name: tensor.detach().contiguous()
        for name, tensor in agent.network.state_dict().items()
        if name.split(".", 1)[0] in TRAINABLE_PARTS
    }


def save_lora_adapter(agent: nn.Module, folder: str | Path) -> Path:
    """Write the LLM adapter (peft format) and the projector / grounding head to `folder/adapter`."""
    from safetensors.torch import save_file

    if not has_lora(agent):
        raise ValueError("no LoRA adapter to save: call attach_lora first")
    out = Path(folder) / ADAPTER_DIR_NAME
    agent.network.language_model.save_pretrained(str(out))
    save_file(_trainables_state(agent), str(out / TRAINABLES_NAME))
    logger.info("saved the LoRA adapter to %s", out)
    return out


def load_lora_adapter(agent: nn.Module, folder: str | Path) -> nn.Module:
    """Attach a saved adapter (from `save_lora_adapter`) to an agent with the base weights; returns it."""
    from peft import PeftModel
    from safetensors.torch import load_file

    folder = Path(folder)
    if (folder / ADAPTER_DIR_NAME).is_dir():
        folder = folder / ADAPTER_DIR_NAME
    if has_lora(agent):
        raise ValueError("LoRA is already attached to this agent")
    if not (folder / "adapter_config.json").is_file():
        raise FileNotFoundError(f"{folder} holds no adapter_config.json (write it with save_lora_adapter)")
    with _without_peft_checkpointing_warning():
        agent.network.language_model = PeftModel.from_pretrained(
            agent.network.language_model, str(folder), is_trainable=True
        )
    trainables = load_file(str(folder / TRAINABLES_NAME))
    result = agent.network.load_state_dict(trainables, strict=False)
    if result.unexpected_keys:
        raise ValueError(f"{folder / TRAINABLES_NAME}: unexpected keys {result.unexpected_keys[:10]}")
    missing = [k for k in result.missing_keys if k.split(".", 1)[0] in TRAINABLE_PARTS]
    if missing:
        raise ValueError(f"{folder / TRAINABLES_NAME}: missing keys {missing[:10]}")
    freeze(agent, STAGE_LORA)
    return agent


def merge_lora(agent: nn.Module) -> nn.Module:
    """Fold the adapters into the LLM weights (peft merge_and_unload); the agent saves as a plain one."""
    if not has_lora(agent):
        raise ValueError("no LoRA adapter to merge: call attach_lora or load_lora_adapter first")
    agent.network.language_model = agent.network.language_model.merge_and_unload()
    logger.info("merged the LoRA adapters into the LLM")
    return agent

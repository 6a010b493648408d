"""What trains and how: the freeze stage or LoRA adapters, activation (gradient) checkpointing, compiled decoder
layers."""

from __future__ import annotations

import logging

from torch import nn

from openfly_agent.model.freeze import freeze
from openfly_agent.model.language.lora import attach_lora
from openfly_agent.training.config import TrainConfig

logger = logging.getLogger(__name__)


def apply_training_mode(agent: nn.Module, cfg: TrainConfig) -> None:
    """Attach LoRA (freeze stage `lora`: it applies the stage) or apply `cfg.freeze_stage`; then gradient
    checkpointing."""
    if cfg.use_lora:
        attach_lora(agent, cfg.lora)
    else:
        freeze(agent, cfg.freeze_stage)
    if cfg.gradient_checkpointing:
        enable_gradient_checkpointing(agent)
    if cfg.compile_layers:
        compile_decoder_layers(agent)


def compile_decoder_layers(agent: nn.Module, backend: str = "inductor") -> int:
    """`torch.compile` each LLM decoder layer in place (`nn.Module.compile`: the parameter names, the state
    dict and the checkpoints stay the same); compiled on the first call. Returns the number of layers."""
    layers = agent.network.causal_lm.model.layers
    for layer in layers:
        layer.compile(backend=backend)
    logger.info("torch.compile (%s) on %d decoder layers", backend, len(layers))
    return len(layers)


def enable_gradient_checkpointing(agent: nn.Module) -> list[str]:
    """Recompute activations in the backward pass: the Llama decoder layers and the timm ViT blocks / ResNet
    stages.

    Non-reentrant checkpointing, so frozen inputs (LoRA, frozen vision) need no `requires_grad` tricks.
    Returns the names of the modules switched on.
    """
    switch_on_decoder_checkpointing(agent)
    switched = [name for name, m in agent.named_modules() if getattr(m, "gradient_checkpointing", False)]
    for name, module in agent.named_modules():
        is_timm = hasattr(module, "set_grad_checkpointing") and hasattr(module, "grad_checkpointing")
        if is_timm and (hasattr(module, "blocks") or hasattr(module, "layer1")):  # a timm ViT or ResNet
            module.set_grad_checkpointing(True)
            switched.append(name)
    logger.info("gradient checkpointing on %d modules", len(switched))
    return switched


def switch_on_decoder_checkpointing(agent: nn.Module) -> None:
    """transformers' non-reentrant checkpointing of the decoder layers, under the name this transformers has:
    `activation_checkpointing_enable` in recent 5.x releases, `gradient_checkpointing_enable` before (5.17,
    seen on a GPU machine, has only the old name; 5.24 keeps it as a deprecated alias)."""
    kwargs = {"use_reentrant": False}
    enable = getattr(agent, "activation_checkpointing_enable", None)
    if enable is not None:
        enable(activation_checkpointing_kwargs=kwargs)
    else:
        agent.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)

"""Named freeze stages: which parts of the agent train. Always logged, never implied."""

from __future__ import annotations

import logging

from torch import nn

logger = logging.getLogger(__name__)

STAGE_FULL = "full"  # everything trains (the released recipe)
STAGE_FROZEN_VISION = "frozen_vision"  # projector + LLM + grounding head
STAGE_HEADS_ONLY = "heads_only"  # the action head (lm_head) + grounding head
STAGE_LORA = "lora"  # LoRA adapters on the LLM + projector + grounding head
FREEZE_STAGES = (STAGE_FULL, STAGE_FROZEN_VISION, STAGE_HEADS_ONLY, STAGE_LORA)

PARTS = ("vision_backbone", "projector", "language_model", "grounding_head")


def _is_lora_parameter(name: str) -> bool:
    return "lora_" in name


def trainable(stage: str, name: str) -> bool:
    """Whether parameter `name` (agent state-dict name) trains in `stage`."""
    part = name.split(".", 1)[0]
    if stage == STAGE_FULL:
        return True
    if stage == STAGE_FROZEN_VISION:
        return part != "vision_backbone"
    if stage == STAGE_HEADS_ONLY:
        return part == "grounding_head" or name.endswith("lm_head.weight")
    if stage == STAGE_LORA:
        return part in ("projector", "grounding_head") or _is_lora_parameter(name)
    raise ValueError(f"unknown freeze stage {stage!r}; use one of {list(FREEZE_STAGES)}")


def freeze(agent: nn.Module, stage: str) -> dict[str, int]:
    """Set `requires_grad` for `stage` and log the outcome.

    Args:
        agent: an `OpenFlyAgent`.
        stage: one of `FREEZE_STAGES`; `lora` needs adapters attached (model/language/lora.py).

    Returns:
        Trainable parameter count per top-level part.
    """
    if stage not in FREEZE_STAGES:
        raise ValueError(f"unknown freeze stage {stage!r}; use one of {list(FREEZE_STAGES)}")
    params = dict(agent.network.named_parameters())  # under the saved names: `projector.*`, ...
    if stage == STAGE_LORA and not any(_is_lora_parameter(n) for n in params):
        raise ValueError(
            "freeze stage 'lora' needs LoRA adapters: call model.lora.attach_lora(agent, settings)"
        )
    counts = dict.fromkeys(PARTS, 0)
    for name, param in params.items():
        param.requires_grad_(trainable(stage, name))
        part = name.split(".", 1)[0]
        if param.requires_grad:
            counts[part] = counts.get(part, 0) + param.numel()
    total = sum(p.numel() for p in params.values())
    logger.info(
        "freeze stage %r: %d of %d parameters train (%s)",
        stage,
        sum(counts.values()),
        total,
        ", ".join(f"{part} {count}" for part, count in counts.items()),
    )
    return counts

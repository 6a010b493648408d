"""Instruction generation: split at action transitions, name landmarks, fuse (template or VLM backend)."""

from __future__ import annotations

from openfly_agent.toolchain.config import InstructionConfig
from openfly_agent.toolchain.instructions.segments import InstructionRequest, split_at_transitions
from openfly_agent.toolchain.instructions.template import TemplateInstructionBackend, template_instruction
from openfly_agent.toolchain.instructions.vlm import VLMError, VLMInstructionBackend


def make_instruction_backend(cfg: InstructionConfig):
    """`template` (offline default) or `vlm` (OpenAI-compatible; key from the environment)."""
    if cfg.backend == "template":
        return TemplateInstructionBackend(cfg.mention_distance)
    if cfg.backend == "vlm":
        return VLMInstructionBackend(cfg.vlm)
    raise ValueError(f"unknown instruction backend {cfg.backend!r}; use 'template' or 'vlm'")


__all__ = [
    "InstructionRequest",
    "TemplateInstructionBackend",
    "VLMError",
    "VLMInstructionBackend",
    "make_instruction_backend",
    "split_at_transitions",
    "template_instruction",
]

"""The RL stage's reference policy: the `init.checkpoint` policy its KL term pulls toward, never trained.

Both forms are called as the agent is, `reference(batch, outputs=outputs)` (its training forward):
- full fine-tuning (every freeze stage but `lora`; the tiny preset): a frozen copy of the prepared agent, made
  before the run's first update or its resume, so it runs on the run's device under the run's autocast;
- LoRA (`freeze_stage=lora`; the 7B configs): the trained model itself with its adapters disabled (peft's
  `disable_adapter()`) and the other tensors the stage trains (the projector and the grounding head) read from
  copies of their starting values (`torch.func.functional_call`). No second copy of the base weights: at 7B the
  copies are the projector's 71 M and the grounding head's 3.5 M parameters, not 7.5 B.

"Adapters off" is the starting policy only when the adapters add nothing at the start. An RL run attaches fresh
adapters to the full weights of `init.checkpoint` (`attach_lora`: a navigation checkpoint of a full run, a LoRA
run's `<run>/merged` with its adapters folded in, or an OpenVLA folder), and peft's `gaussian` and `default`
inits start each `lora_B` at zero, so `B @ A = 0`. Inits that start the adapters non-zero and change the base
weights to match (PiSSA, OLoRA, LoftQ, ...) would make "adapters off" another policy: they are refused.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

from torch import nn
from torch.func import functional_call

from openfly_agent.model.language.lora import has_lora
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.preflight import PreflightError

LORA_MARKER = "lora_"  # in the name of every adapter tensor (peft), as model/freeze.py tells them apart
LORA_B_MARKER = "lora_B"


class AdaptersOff:
    """The LoRA run's reference: `model` with its adapters disabled and its other trainable tensors at their
    values when this object was made (the run's start; make it before a resume restores the trained ones)."""

    def __init__(self, model: nn.Module, language_model: nn.Module, lora_init: str) -> None:
        started = [
            name
            for name, param in model.named_parameters()
            if LORA_B_MARKER in name and bool(param.detach().any())
        ]
        if started:
            raise PreflightError(
                f"stage=rl with LoRA needs adapters that start at zero (its KL reference is the model with its "
                f"adapters off), but lora.init={lora_init} starts {len(started)} of them non-zero (e.g. "
                f"{started[0]}): use lora.init=gaussian"
            )
        self.model = model
        self.language_model = language_model  # the peft model whose adapters the reference disables
        self.starting = {  # name -> the starting value of each trained tensor outside the adapters
            name: param.detach().clone()
            for name, param in model.named_parameters()
            if param.requires_grad and LORA_MARKER not in name
        }

    def __call__(self, batch: dict, outputs: dict | None = None):
        with self.language_model.disable_adapter():
            return functional_call(self.model, self.starting, (batch,), {"outputs": outputs}, strict=False)


def make_reference(cfg: TrainConfig, model: nn.Module, agent: nn.Module) -> Callable:
    """The reference of a run whose prepared model is `model` (`agent`: the agent inside it), before any
    update or resume: `AdaptersOff` for a LoRA run, else a frozen copy (module docstring)."""
    if cfg.use_lora and has_lora(agent):
        return AdaptersOff(model, agent.network.language_model, cfg.lora.init)
    frozen = copy.deepcopy(model).eval()
    return frozen.requires_grad_(False)


def describe_reference(reference: Callable) -> str:
    """What the reference is and what it holds of its own, for the log."""
    if isinstance(reference, AdaptersOff):
        own = sum(t.numel() for t in reference.starting.values())
        return (
            "the trained model with its LoRA adapters off and its other trained tensors at their start "
            f"({own:,} parameters copied)"
        )
    copied = sum(t.numel() for t in reference.parameters())
    return f"a frozen copy of the starting agent ({copied:,} parameters)"

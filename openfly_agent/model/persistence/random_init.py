"""Materialise an agent built on the meta device with random weights (benchmarks of shapes with no weights here).

Building on `torch.device("meta")` and materialising once on the target device avoids a full-size CPU copy of a
7B model; `materialize_random_` then gives every tensor a value: matrices N(0, 0.02), norm weights 1, LayerScale
`gamma` 1e-5, biases 0, and the rotary embedding's buffers recomputed by the LLM's own initialiser.
"""

from __future__ import annotations

import torch
from torch import nn

INIT_STD = 0.02
LAYER_SCALE_INIT = 1e-5


@torch.no_grad()
def materialize_random_(
    agent: nn.Module, device: str | torch.device, dtype: torch.dtype | None = None
) -> nn.Module:
    """Allocate `agent`'s meta tensors on `device` (cast to `dtype` when given) and fill them; returns `agent`."""
    agent.to_empty(device=device)
    if dtype is not None:
        agent.to(dtype)
    for module in agent.modules():
        if type(module).__name__.endswith("RotaryEmbedding"):
            agent.network.language_model._init_weights(module)
    for name, param in agent.named_parameters():
        if param.ndim >= 2:
            param.normal_(0.0, INIT_STD)
        else:  # norm weights 1, LayerScale small, biases 0
            param.fill_(
                1.0 if name.endswith("weight") else LAYER_SCALE_INIT if name.endswith("gamma") else 0.0
            )
    return agent

"""Vision-to-LLM projector: Prismatic's fused GELU MLP (`fc1`, `fc2`, `fc3`, the OpenVLA key names)."""

from __future__ import annotations

import torch
from torch import nn

# fc1's width as a multiple of the vision width: OpenVLA's 4 x 2176 = 8704 (a setting until issue 46, which no
# config or experiment changed).
HIDDEN_RATIO = 4


class FusedMLPProjector(nn.Module):
    """fc1 (D_v -> 4 D_v) -> GELU -> fc2 (-> D_llm) -> GELU -> fc3 (D_llm -> D_llm).

    Args:
        vision_dim: fused vision feature width (2176 for dinosiglip-224px).
        llm_dim: LLM hidden size.
    """

    def __init__(self, vision_dim: int, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, HIDDEN_RATIO * vision_dim)
        self.fc2 = nn.Linear(HIDDEN_RATIO * vision_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(..., D_v) -> (..., D_llm)."""
        features = features.to(self.fc1.weight.dtype)
        return self.fc3(self.act(self.fc2(self.act(self.fc1(features)))))

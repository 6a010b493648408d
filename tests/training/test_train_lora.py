"""Folding LoRA into base weights from the in-memory state dict: merged outputs equal the adapter's."""

from __future__ import annotations

import pytest
import torch
from peft import LoraConfig, get_peft_model
from torch import nn

from openfly_agent.training.lora import lora_scalings, merge_lora_state_dict, strip_peft_prefixes


class _Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.inner = nn.Sequential(nn.Linear(4, 8), nn.GELU(), nn.Linear(8, 3))
        self.head = nn.Linear(3, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.inner(x))


def test_merged_state_dict_reproduces_adapter_outputs():
    base, plain = _Net(), _Net()
    plain.load_state_dict(base.state_dict())
    lora_cfg = LoraConfig(r=2, lora_alpha=6, target_modules=["inner.0", "inner.2"], init_lora_weights=False)
    adapted = get_peft_model(base, lora_cfg)
    scalings = lora_scalings(adapted)
    assert set(scalings.values()) == {3.0}  # alpha / r
    merged = merge_lora_state_dict(adapted.state_dict(), scalings)
    assert sorted(merged) == sorted(plain.state_dict())
    plain.load_state_dict(merged)
    x = torch.randn(5, 4)
    torch.testing.assert_close(plain(x), adapted(x), atol=1e-5, rtol=1e-5)
    delta = merged["inner.0.weight"] - adapted.state_dict()["base_model.model.inner.0.base_layer.weight"]
    assert delta.abs().max() > 1e-3  # the adapter really changed the weight


def test_merge_rejects_unsupported_adapters_and_missing_scaling():
    with pytest.raises(ValueError, match="only Linear LoRA"):
        merge_lora_state_dict({"m.lora_magnitude_vector.default.weight": torch.zeros(1)}, {})
    state = {
        "m.base_layer.weight": torch.zeros(2, 2),
        "m.lora_A.default.weight": torch.zeros(1, 2),
        "m.lora_B.default.weight": torch.zeros(2, 1),
    }
    with pytest.raises(ValueError, match="lacks"):
        merge_lora_state_dict(state, {})


def test_strip_peft_prefixes():
    key = "language_model.base_model.model.model.layers.0.q_proj.base_layer.weight"
    assert strip_peft_prefixes(key) == "language_model.model.layers.0.q_proj.weight"
    assert strip_peft_prefixes("base_model.model.head.bias") == "head.bias"

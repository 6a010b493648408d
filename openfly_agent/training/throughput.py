"""Model FLOPs of a training step and model FLOPs utilisation (MFU): the one accounting of `train.py`'s log and
`bench/train_throughput.py`.

Model FLOPs count the matrix products a step needs, whatever the implementation does (the PaLM convention):

- **vision backbone**: the forward FLOPs of one frame (`vision_frame`, counted once by PyTorch's FLOP counter
  on a meta-device copy of the backbone: convolutions and matmuls) times the frames the batch encodes (each
  row's current frame, or the distinct frames of a grounding batch, plus every real memory frame). Backward:
  none when the backbone is frozen (nothing before it trains); else the input gradients (1x forward) plus the
  weight gradients of its trainable share.
- **projector and LLM decoder layers**: 2 N FLOPs per token forward, where N counts the weights of their
  matrices (LoRA's A and B included; embeddings, norms and the LM head, which runs at a few positions only,
  excluded); backward 2 N per token for the input gradients when anything at or before the module trains,
  plus 2 N_trainable per token for the weight gradients. A full fine-tune is the familiar 6 N per token;
  LoRA on a frozen base is 4 N + 2 N_lora (+ the adapters' own 4 N_lora of forward and input gradients).
- **attention** (no weights): 4 L d T^2 forward per row of T tokens (scores and weighted values over the full
  square, as PyTorch's counter counts SDPA), twice that backward.

Each row's T is its real tokens (`llm_row_tokens`): padding is not counted. Activations that gradient
checkpointing recomputes are **not** counted (they are hardware FLOPs, not model FLOPs), so a checkpointed
run's MFU is what an uncheckpointed run at the same speed would show. The grounding head, the box token,
token merging and pooling are left out (under 1 % of the 7B step). MFU divides model FLOPs per second by the
device's bf16 dense datasheet peak (`PEAK_BF16_TFLOPS`, matched by the CUDA device name) whatever the run's
precision; on the CPU and on unknown GPUs there is no peak and no MFU.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from openfly_agent import constants as C

# bf16 dense tensor-core peaks (datasheets, TFLOP/s), matched as substrings of the CUDA device name
PEAK_BF16_TFLOPS = {
    "H100": 989.0,
    "H200": 989.0,
    "A100": 312.0,
    "L40S": 362.0,
    "A10": 125.0,
    "4090": 165.0,
}


def device_peak_flops(device: torch.device | str, override_tflops: float | None = None) -> float | None:
    """The bf16 dense peak of `device` in FLOP/s: `override_tflops` when given, else the table's entry for a
    CUDA device's name; None on the CPU and on GPUs the table lacks (never a guess)."""
    if override_tflops:
        return override_tflops * 1e12
    device = torch.device(device)
    if device.type != "cuda":
        return None
    name = torch.cuda.get_device_name(device)
    for key, tflops in PEAK_BF16_TFLOPS.items():
        if key in name:
            return tflops * 1e12
    return None


def mfu(flops: float, seconds: float, peak_flops: float | None) -> float | None:
    """Model FLOPs utilisation: `flops` done in `seconds` over the peak (None without a peak)."""
    if peak_flops is None or seconds <= 0:
        return None
    return flops / seconds / peak_flops


def llm_row_tokens(batch: dict, model_cfg) -> torch.Tensor:
    """(B,) LLM sequence positions of each row: text tokens (attention mask) + visual tokens.

    Visual tokens = the current frame's P patch tokens + `memory_tokens_per_set` for every memory set that
    holds at least one real frame (an empty set contributes nothing). Stays on the batch's device (no sync).
    """
    text = batch[C.ATTENTION_MASK].sum(dim=1)  # (B,)
    visual = torch.full_like(text, model_cfg.vision.num_patches)
    if C.MEMORY_FRAME_MASK in batch:
        sets = batch[C.MEMORY_FRAME_MASK].any(dim=-1).sum(dim=-1)  # (B, K, S) -> (B,) sets with a real frame
        visual = visual + sets.to(text.device) * model_cfg.memory_tokens_per_set
    return text + visual


def encoded_frames(batch: dict) -> int | torch.Tensor:
    """The frames a training batch runs through the vision backbone (current + real memory): an int, or a 0-d
    tensor on the batch's device (no copy to or from the host)."""
    frames = batch[C.PIXEL_VALUES].shape[0]
    if C.MEMORY_FRAME_MASK in batch:
        return batch[C.MEMORY_FRAME_MASK].sum() + frames
    return frames


def _matrix_params(module: nn.Module | None) -> tuple[int, int]:
    """(all, trainable) weights of the matrices of `module` (parameters of 2 or more dimensions)."""
    if module is None:
        return 0, 0
    matrices = [p for p in module.parameters() if p.dim() >= 2]
    return sum(p.numel() for p in matrices), sum(p.numel() for p in matrices if p.requires_grad)


def _trains(module: nn.Module | None) -> bool:
    return module is not None and any(p.requires_grad for p in module.parameters())


def vision_frame_flops(vision_cfg) -> float:
    """Forward FLOPs of one frame through the backbone of `vision_cfg`, counted on a meta-device copy (no
    weights allocated, nothing of the trained agent touched)."""
    from torch.utils.flop_counter import FlopCounterMode

    from openfly_agent.model.vision.backbone import build_vision_backbone  # lazy: timm

    with torch.device("meta"):
        backbone = build_vision_backbone(vision_cfg).eval()
    side = vision_cfg.image_size
    pixels = torch.zeros(1, 3, side, side, dtype=torch.uint8, device="meta")
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        backbone.forward_with_cls(pixels)
    return float(counter.get_total_flops())


@dataclass(frozen=True)
class StepFlops:
    """The constants of the model-FLOP count of one agent as it trains (which parts train fixes the backward).

    Attributes:
        vision_frame: forward FLOPs of one frame through the vision backbone.
        vision_backward: backward FLOPs per forward FLOP of the backbone (0 when frozen).
        projector_params, projector_trainable: matrix weights of the projector (all, trainable).
        projector_input_grads: the backbone trains, so gradients flow through the projector into it.
        llm_params, llm_trainable: matrix weights of the decoder layers (all, trainable; LoRA included).
        llm_input_grads: something at or before the decoder layers trains.
        layers, width: decoder layers and hidden size (the attention term).
        model_cfg: the model sections that say how many visual tokens a row has.
    """

    vision_frame: float
    vision_backward: float
    projector_params: int
    projector_trainable: int
    projector_input_grads: bool
    llm_params: int
    llm_trainable: int
    llm_input_grads: bool
    layers: int
    width: int
    model_cfg: object

    @classmethod
    def from_agent(cls, agent: nn.Module) -> StepFlops:
        """The count of `agent` (an `OpenFlyAgent`, before accelerate wraps it) with its freeze / LoRA applied."""
        cfg = agent.model_cfg
        vision_all = sum(p.numel() for p in agent.network.vision_backbone.parameters())
        vision_trainable = sum(
            p.numel() for p in agent.network.vision_backbone.parameters() if p.requires_grad
        )
        vision_trains = vision_trainable > 0
        layers = agent.network.causal_lm.model.layers
        projector_params, projector_trainable = _matrix_params(agent.network.projector)
        llm_params, llm_trainable = _matrix_params(layers)
        return cls(
            vision_frame=vision_frame_flops(cfg.vision),
            vision_backward=(1.0 + vision_trainable / vision_all) if vision_trains else 0.0,
            projector_params=projector_params,
            projector_trainable=projector_trainable,
            projector_input_grads=vision_trains,
            llm_params=llm_params,
            llm_trainable=llm_trainable,
            llm_input_grads=vision_trains or _trains(agent.network.projector) or _trains(layers),
            layers=len(layers),
            width=cfg.llm.hidden_size,
            model_cfg=cfg,
        )

    def flops(self, frames, row_tokens: torch.Tensor, visual_tokens) -> torch.Tensor:
        """Model FLOPs of one forward + backward (see the module docstring).

        Args:
            frames: frames through the vision backbone (int or 0-d tensor).
            row_tokens: (B,) LLM tokens of each row.
            visual_tokens: tokens through the projector (int or 0-d tensor).

        Returns:
            A 0-d float64 tensor on `row_tokens`' device (read it at a log step: no sync before).
        """
        tokens = row_tokens.to(torch.float64)
        vision = self.vision_frame * (1.0 + self.vision_backward) * frames
        projector_per_token = 2 * (
            self.projector_params * (1 + self.projector_input_grads) + self.projector_trainable
        )
        llm_per_token = 2 * (self.llm_params * (1 + self.llm_input_grads) + self.llm_trainable)
        attention = 4 * self.layers * self.width * (1 + 2 * self.llm_input_grads)  # per row, times T^2
        llm = llm_per_token * tokens.sum() + attention * (tokens**2).sum()
        return llm + projector_per_token * visual_tokens + vision

    def batch_flops(self, batch: dict) -> torch.Tensor:
        """Model FLOPs of one forward + backward of a training micro-batch (0-d tensor on its device)."""
        rows = llm_row_tokens(batch, self.model_cfg)
        text = batch[C.ATTENTION_MASK].sum()
        return self.flops(encoded_frames(batch), rows, rows.sum() - text)

"""The `tiny-cnn` vision backbone: a small timm ResNet that yields the same token grid as the ViT presets.

A from-scratch ViT learns slowly at the tiny scale on a CPU; a convolutional network has the locality prior
built in (docs/experiments/2026-11-23-agent-that-navigates-issue12.md, "Tiny backbones"). The ResNet's four stages downsample by 16 (the last stage is
dilated instead of strided), so a 128 px frame gives an 8 x 8 grid, the patch grid of a ViT with patch 16; a
learned position embedding is added to every cell (convolution features alone say little about *where* a cell
is, and the LLM's rotary positions only give relative offsets). The output (N, P, C) goes into the same
projector and LLM as the ViT features. Runs channels-last (oneDNN's fast path on CPUs). With `vision.cnn_colour_stats` each token also gets a projection of its cell's colour statistics
(`cell_colour_stats`): trained from scratch on these objectives the ResNet's features lose a landmark's colour
(a linear probe reads it from them at chance, from the cell's raw RGB statistics at 0.72), and colour is half of
what tells one landmark of an instruction from its neighbours.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from transformers import initialization as init

from openfly_agent.model.config import CNN_STEM_PATCH4, CNN_STRIDE, TinyCnnVisionConfig, VisionConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)  # input normalisation (DINOv2 and the ResNet)
IMAGENET_STD = (0.229, 0.224, 0.225)
COLOUR_STATS = 18  # per cell: mean and standard deviation of the 3 channels, the means of its 2 x 2 quarters


def normalised_pixels(pixels: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(F, 3, H, W) uint8 RGB -> the ResNet's input: [0, 1] scaled, then ImageNet mean and std per channel."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=dtype, device=pixels.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=dtype, device=pixels.device).view(1, 3, 1, 1)
    return (pixels.to(dtype) / 255.0 - mean) / std


def cell_colour_stats(x: torch.Tensor, cell: int) -> torch.Tensor:
    """Normalised (F, 3, H, W) pixels -> (F, COLOUR_STATS, H / cell, W / cell) colour statistics of each cell:
    the channel means, the channel standard deviations and the channel means of the cell's 2 x 2 quarters."""
    x = x.contiguous()  # the reshapes below assume the default layout
    mean = F.avg_pool2d(x, cell)  # (F, 3, g, g)
    std = (F.avg_pool2d(x * x, cell) - mean * mean).clamp_min(0.0).add(1e-6).sqrt()  # (F, 3, g, g)
    quarters = F.avg_pool2d(x, cell // 2)  # (F, 3, 2g, 2g)
    n, channels, side = quarters.shape[0], quarters.shape[1], quarters.shape[2] // 2
    quarters = (
        quarters.reshape(n, channels, side, 2, side, 2)
        .permute(0, 1, 3, 5, 2, 4)
        .reshape(n, 4 * channels, side, side)
    )  # (F, 12, g, g), channel-major, then quarter row, quarter column
    return torch.cat([mean, std, quarters], dim=1)


def build_resnet(channels: tuple[int, ...], stem: str) -> nn.Module:
    """A timm ResNet of BasicBlocks, one block per stage, output stride 16, no pooling or classifier.

    `stem` = `patch4` swaps timm's stem (7 x 7 stride-2 conv, then a 3 x 3 stride-2 max pool) for one 4 x 4
    stride-4 conv: the same 64 channels at the same stride 4 into the first stage, without the two
    full-resolution maps (half the input side, 64 channels) whose conv, BN, ReLU and pool dominate a CPU step.
    """
    from timm.models.resnet import BasicBlock, ResNet

    if len(channels) != 4:
        raise ValueError(f"vision.cnn_channels needs 4 stage widths, got {list(channels)}")
    net = ResNet(
        BasicBlock,
        [1, 1, 1, 1],
        channels=tuple(channels),
        output_stride=CNN_STRIDE,
        num_classes=0,
        global_pool="",
    )
    if stem == CNN_STEM_PATCH4:
        net.conv1 = nn.Conv2d(
            3, net.conv1.out_channels, kernel_size=4, stride=4, bias=False
        )  # (F, 64, H/4, W/4)
        net.maxpool = nn.Identity()
    return net


@TinyCnnVisionConfig.register_builder
class ConvVisionBackbone(nn.Module):
    """`featurizer` (a small ResNet) + `pos_embed`: uint8 pixels -> (N, P, C) cell features.

    Args:
        cfg: vision section of the model config (`tiny-cnn`: image_size, cnn_channels, cnn_stem).
    """

    def __init__(self, cfg: VisionConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.image_size = cfg.image_size
        self.featurizer = build_resnet(tuple(cfg.cnn_channels), cfg.cnn_stem).to(
            memory_format=torch.channels_last
        )
        self.grid_side = cfg.grid_side
        self.pos_embed = nn.Parameter(torch.zeros(cfg.num_patches, cfg.cnn_channels[-1]))
        self.colour_proj = nn.Linear(COLOUR_STATS, cfg.cnn_channels[-1]) if cfg.cnn_colour_stats else None
        # no buffers for the constants: transformers builds models on the meta device when loading, and a
        # non-persistent buffer would come back uninitialised

    @torch.no_grad()
    def init_weights(self) -> None:
        """Fresh init, run by the agent after its generic one (every conv N(0, 0.02), every BN gamma 1): the
        position embedding. transformers' init functions skip tensors loaded from a checkpoint."""
        init.trunc_normal_(self.pos_embed, std=0.02)

    @property
    def feature_dim(self) -> int:
        """C, the width of each cell feature."""
        return self.pos_embed.shape[-1]

    def forward(self, pixels: torch.Tensor, frame_index: torch.Tensor | None = None) -> torch.Tensor:
        """(F, 3, H, W) uint8 RGB -> (N, P, C) features of the (H / 16) x (W / 16) cells, row-major.

        Args:
            pixels: the frames.
            frame_index: (N,) long, the frame each sequence reads (None: N = F, sequence i reads frame i).
        """
        size = self.image_size
        if pixels.dtype != torch.uint8 or pixels.ndim != 4 or tuple(pixels.shape[1:]) != (3, size, size):
            raise ValueError(
                f"vision backbone expects uint8 RGB pixels of shape (N, 3, {size}, {size}); got "
                f"{pixels.dtype} {tuple(pixels.shape)}"
            )
        x = normalised_pixels(pixels, self.pos_embed.dtype).contiguous(memory_format=torch.channels_last)
        features = self.featurizer.forward_features(x)  # (F, C, g, g)
        if frame_index is not None:
            features = features[frame_index.to(features.device)]  # (N, C, g, g)
        tokens = features.flatten(2).transpose(1, 2) + self.pos_embed.to(features.dtype)  # (N, P, C)
        if self.colour_proj is None:
            return tokens
        colour = cell_colour_stats(x, CNN_STRIDE).flatten(2).transpose(1, 2)  # (F, P, COLOUR_STATS)
        if frame_index is not None:
            colour = colour[frame_index.to(colour.device)]  # (N, P, COLOUR_STATS)
        return tokens + self.colour_proj(colour)

    def forward_with_cls(self, pixels: torch.Tensor) -> tuple[torch.Tensor, None]:
        """The ViT backbones' `(patches, cls)` interface; a CNN has no CLS token (None)."""
        return self.forward(pixels), None

    def set_grad_checkpointing(self, enable: bool = True) -> None:
        """Activation checkpointing of the ResNet stages (timm)."""
        self.featurizer.set_grad_checkpointing(enable)

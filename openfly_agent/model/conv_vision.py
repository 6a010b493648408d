"""The `tiny-cnn` vision backbone: a small timm ResNet that yields the same token grid as the ViT presets.

A from-scratch ViT learns slowly at the tiny scale on a CPU; a convolutional network has the locality prior
built in (docs/BENCHMARKS.md, "Tiny preset"). The ResNet's four stages downsample by 16 (the last stage is
dilated instead of strided), so a 128 px frame gives an 8 x 8 grid, the patch grid of a ViT with patch 16; a
learned position embedding is added to every cell (convolution features alone say little about *where* a cell
is, and the LLM's rotary positions only give relative offsets). The output (N, P, C) goes into the same
projector and LLM as the ViT features. Runs channels-last (oneDNN's fast path on CPUs). With
`vision.cnn_fine_fusion` each token also gets the second stage's stride-8 features of the 2 x 2 cells under it
(concatenated, projected by `fine_proj` and added): a landmark of a few pixels keeps its own features.
"""

from __future__ import annotations

import torch
from torch import nn

from .config import CNN_STRIDE, VisionConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)  # input normalisation (DINOv2 and the ResNet)
IMAGENET_STD = (0.229, 0.224, 0.225)


def build_resnet(channels: tuple[int, ...], stem_width: int) -> nn.Module:
    """A timm ResNet of BasicBlocks, one block per stage, output stride 16, no pooling or classifier."""
    from timm.models.resnet import BasicBlock, ResNet

    if len(channels) != 4:
        raise ValueError(f"vision.cnn_channels needs 4 stage widths, got {list(channels)}")
    return ResNet(
        BasicBlock,
        [1, 1, 1, 1],
        channels=tuple(channels),
        stem_width=stem_width,
        output_stride=CNN_STRIDE,
        num_classes=0,
        global_pool="",
    )


class ConvVisionBackbone(nn.Module):
    """`featurizer` (a small ResNet) + `pos_embed`: uint8 pixels -> (N, P, C) cell features.

    Args:
        cfg: vision section of the model config (`tiny-cnn`: image_size, cnn_channels, cnn_stem_width).
    """

    def __init__(self, cfg: VisionConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.image_size = cfg.image_size
        self.featurizer = build_resnet(tuple(cfg.cnn_channels), cfg.cnn_stem_width).to(
            memory_format=torch.channels_last
        )
        self.grid_side = cfg.grid_side
        self.pos_embed = nn.Parameter(torch.zeros(cfg.num_patches, cfg.cnn_channels[-1]))
        # the second stage (stride 8) under each token: 2 x 2 cells of cnn_channels[1], to the token width
        self.fine_proj = (
            nn.Linear(4 * cfg.cnn_channels[1], cfg.cnn_channels[-1]) if cfg.cnn_fine_fusion else None
        )
        # no buffers for the constants: transformers builds models on the meta device when loading, and a
        # non-persistent buffer would come back uninitialised

    @property
    def feature_dim(self) -> int:
        """C, the width of each cell feature."""
        return self.pos_embed.shape[-1]

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) uint8 RGB -> (N, P, C) features of the (H / 16) x (W / 16) cells, row-major."""
        size = self.image_size
        if pixels.dtype != torch.uint8 or pixels.ndim != 4 or tuple(pixels.shape[1:]) != (3, size, size):
            raise ValueError(
                f"vision backbone expects uint8 RGB pixels of shape (N, 3, {size}, {size}); got "
                f"{pixels.dtype} {tuple(pixels.shape)}"
            )
        dtype, device = self.pos_embed.dtype, pixels.device
        mean = torch.tensor(IMAGENET_MEAN, dtype=dtype, device=device).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD, dtype=dtype, device=device).view(1, 3, 1, 1)
        x = ((pixels.to(dtype) / 255.0 - mean) / std).contiguous(memory_format=torch.channels_last)
        if self.fine_proj is None:
            features = self.featurizer.forward_features(x)  # (N, C, g, g)
        else:  # stage index 2 = layer2, stride 8: (N, C_1, 2g, 2g) -> (N, 4 C_1, g, g) -> (N, C, g, g)
            features, (fine,) = self.featurizer.forward_intermediates(x, indices=[2])
            n, c, side = fine.shape[0], fine.shape[1], fine.shape[2] // 2
            # each token's 2 x 2 cells, channel-major (pixel_unshuffle's order; its backward aborts on
            # channels-last tensors in torch 2.13)
            fine = (
                fine.reshape(n, c, side, 2, side, 2).permute(0, 2, 4, 1, 3, 5).reshape(n, side, side, 4 * c)
            )
            features = features + self.fine_proj(fine).permute(0, 3, 1, 2)
        return features.flatten(2).transpose(1, 2) + self.pos_embed.to(features.dtype)  # (N, P, C)

    def forward_with_cls(self, pixels: torch.Tensor) -> tuple[torch.Tensor, None]:
        """The ViT backbones' `(patches, cls)` interface; a CNN has no CLS token (None)."""
        return self.forward(pixels), None

    def set_grad_checkpointing(self, enable: bool = True) -> None:
        """Activation checkpointing of the ResNet stages (timm)."""
        self.featurizer.set_grad_checkpointing(enable)

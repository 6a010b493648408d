"""The `tiny-cnn` vision backbone: a small timm ResNet that yields the same token grid as the ViT presets.

A from-scratch ViT learns slowly at the tiny scale on a CPU; a convolutional network has the locality prior
built in (docs/experiments/2026-11-23-agent-that-navigates-issue12.md, "Tiny backbones"). The ResNet's four stages downsample by 16 (the last stage is
dilated instead of strided), so a 128 px frame gives an 8 x 8 grid, the patch grid of a ViT with patch 16; a
learned position embedding is added to every cell (convolution features alone say little about *where* a cell
is, and the LLM's rotary positions only give relative offsets). The output (N, P, C) goes into the same
projector and LLM as the ViT features. Runs channels-last (oneDNN's fast path on CPUs). With
`vision.cnn_fine_fusion` each token also gets the second stage's stride-8 features of the 2 x 2 cells under it
(concatenated, projected by `fine_proj` and added): a landmark of a few pixels keeps its own features. With
`vision.cnn_instruction_film` the third and fourth stages run once per sequence, their inputs scaled and shifted
by the instruction (model/vision/instruction_film.py); the stem and the first two stages still run once per frame.
With `vision.cnn_colour_stats` each token also gets a projection of its cell's colour statistics
(`cell_colour_stats`): trained from scratch on these objectives the ResNet's features lose a landmark's colour
(a linear probe reads it from them at chance, from the cell's raw RGB statistics at 0.72), and colour is half of
what tells one landmark of an instruction from its neighbours.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from transformers import initialization as init

from openfly_agent.model.config import CNN_INIT_TIMM, CNN_STEM_PATCH4, CNN_STRIDE, VisionConfig
from openfly_agent.model.vision.instruction_film import InstructionFiLM

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


def build_resnet(channels: tuple[int, ...], stem_width: int, stem: str) -> nn.Module:
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
        stem_width=stem_width,
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


class ConvVisionBackbone(nn.Module):
    """`featurizer` (a small ResNet) + `pos_embed`: uint8 pixels -> (N, P, C) cell features.

    Args:
        cfg: vision section of the model config (`tiny-cnn`: image_size, cnn_channels, cnn_stem_width).
        text_dim: width of the instruction code (the LLM's embedding width; needed by `cnn_instruction_film`).
    """

    def __init__(self, cfg: VisionConfig, text_dim: int | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.image_size = cfg.image_size
        self.featurizer = build_resnet(tuple(cfg.cnn_channels), cfg.cnn_stem_width, cfg.cnn_stem).to(
            memory_format=torch.channels_last
        )
        self.grid_side = cfg.grid_side
        self.pos_embed = nn.Parameter(torch.zeros(cfg.num_patches, cfg.cnn_channels[-1]))
        # the second stage (stride 8) under each token: 2 x 2 cells of cnn_channels[1], to the token width
        self.fine_proj = (
            nn.Linear(4 * cfg.cnn_channels[1], cfg.cnn_channels[-1]) if cfg.cnn_fine_fusion else None
        )
        self.colour_proj = nn.Linear(COLOUR_STATS, cfg.cnn_channels[-1]) if cfg.cnn_colour_stats else None
        self.instruction_film = None
        if cfg.cnn_instruction_film:
            if not text_dim:
                raise ValueError("vision.cnn_instruction_film needs the width of the instruction code")
            # the inputs of the third and fourth stages: the outputs of the second and third
            self.instruction_film = InstructionFiLM(text_dim, (cfg.cnn_channels[1], cfg.cnn_channels[2]))
        # no buffers for the constants: transformers builds models on the meta device when loading, and a
        # non-persistent buffer would come back uninitialised

    @torch.no_grad()
    def init_weights(self) -> None:
        """Fresh init, run by the agent after its generic one (every conv N(0, 0.02), every BN gamma 1): the
        position embedding, the instruction FiLM at the identity and, with `vision.cnn_init=timm`, timm's own
        ResNet init (Kaiming-normal convs, fan-out; the last BN of each residual branch zero, so every block
        starts as its shortcut). transformers' init functions skip tensors loaded from a checkpoint."""
        from timm.models.resnet import BasicBlock

        init.trunc_normal_(self.pos_embed, std=0.02)
        if self.instruction_film is not None:
            self.instruction_film.reset_to_identity()
        if self.cfg.cnn_init != CNN_INIT_TIMM:
            return
        for module in self.featurizer.modules():
            if isinstance(module, nn.Conv2d):
                init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, BasicBlock):
                init.zeros_(module.bn2.weight)

    @property
    def feature_dim(self) -> int:
        """C, the width of each cell feature."""
        return self.pos_embed.shape[-1]

    def forward(
        self,
        pixels: torch.Tensor,
        instruction: torch.Tensor | None = None,
        frame_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(F, 3, H, W) uint8 RGB -> (N, P, C) features of the (H / 16) x (W / 16) cells, row-major.

        Args:
            pixels: the frames.
            instruction: (N, D_text) instruction code of each sequence (`cnn_instruction_film` only, needed).
            frame_index: (N,) long, the frame each sequence reads (None: N = F, sequence i reads frame i).
        """
        size = self.image_size
        if pixels.dtype != torch.uint8 or pixels.ndim != 4 or tuple(pixels.shape[1:]) != (3, size, size):
            raise ValueError(
                f"vision backbone expects uint8 RGB pixels of shape (N, 3, {size}, {size}); got "
                f"{pixels.dtype} {tuple(pixels.shape)}"
            )
        if (instruction is None) != (self.instruction_film is None):
            raise ValueError(
                "an instruction code goes with vision.cnn_instruction_film and only with it "
                f"(option {'on' if self.instruction_film is not None else 'off'})"
            )
        x = normalised_pixels(pixels, self.pos_embed.dtype).contiguous(memory_format=torch.channels_last)
        if self.instruction_film is not None:
            features = self._conditioned_features(x, instruction, frame_index)  # (N, C, g, g)
        else:
            features = self._frame_features(x)  # (F, C, g, g)
            if frame_index is not None:
                features = features[frame_index.to(features.device)]  # (N, C, g, g)
        tokens = features.flatten(2).transpose(1, 2) + self.pos_embed.to(features.dtype)  # (N, P, C)
        if self.colour_proj is None:
            return tokens
        colour = cell_colour_stats(x, CNN_STRIDE).flatten(2).transpose(1, 2)  # (F, P, COLOUR_STATS)
        if frame_index is not None:
            colour = colour[frame_index.to(colour.device)]  # (N, P, COLOUR_STATS)
        return tokens + self.colour_proj(colour)

    def _frame_features(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised (F, 3, H, W) -> (F, C, g, g), without instruction."""
        if self.fine_proj is None:
            return self.featurizer.forward_features(x)  # (F, C, g, g)
        # stage index 2 = layer2, stride 8: (F, C_1, 2g, 2g) -> (F, 4 C_1, g, g) -> (F, C, g, g)
        features, (fine,) = self.featurizer.forward_intermediates(x, indices=[2])
        n, c, side = fine.shape[0], fine.shape[1], fine.shape[2] // 2
        # each token's 2 x 2 cells, channel-major (pixel_unshuffle's order; its backward aborts on channels-last
        # tensors in torch 2.13)
        fine = fine.reshape(n, c, side, 2, side, 2).permute(0, 2, 4, 1, 3, 5).reshape(n, side, side, 4 * c)
        return features + self.fine_proj(fine).permute(0, 3, 1, 2)

    def _conditioned_features(
        self, x: torch.Tensor, instruction: torch.Tensor, frame_index: torch.Tensor | None
    ) -> torch.Tensor:
        """Normalised (F, 3, H, W) -> (N, C, g, g): stem and stages 1-2 per frame, stages 3-4 per sequence."""
        net = self.featurizer
        x = net.layer2(net.layer1(net.maxpool(net.act1(net.bn1(net.conv1(x))))))  # (F, C_1, 2g, 2g)
        if frame_index is not None:
            x = x[frame_index.to(x.device)]  # (N, C_1, 2g, 2g)
        if instruction.shape[0] != x.shape[0]:
            raise ValueError(f"{instruction.shape[0]} instruction codes for {x.shape[0]} sequences")
        (scale_3, shift_3), (scale_4, shift_4) = self.instruction_film(instruction.to(x.dtype))
        x = net.layer3(x * scale_3 + shift_3)  # (N, C_2, g, g)
        return net.layer4(x * scale_4 + shift_4)  # (N, C, g, g)

    def forward_with_cls(
        self, pixels: torch.Tensor, instruction: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, None]:
        """The ViT backbones' `(patches, cls)` interface; a CNN has no CLS token (None)."""
        return self.forward(pixels, instruction), None

    def set_grad_checkpointing(self, enable: bool = True) -> None:
        """Activation checkpointing of the ResNet stages (timm)."""
        self.featurizer.set_grad_checkpointing(enable)

"""The vision backbones and `build_vision_backbone`, which builds the one a vision section names: the fused
DINOv2 + SigLIP ViTs built with timm (`DinoSiglipBackbone`, `TinyVitBackbone`), uint8 pixels -> fused per-patch
features, or the small ResNet (`ConvVisionBackbone`, model/vision/conv.py). Each is registered as its variant's
builder (model/config_choice.py).

As Prismatic / OpenVLA: both ViTs read the output of their second-to-last block without the final norm
(the later blocks, norms and SigLIP's attention-pool head are pruned, so they hold no parameters), and the
patch features are concatenated channel-wise (1024 + 1152 = 2176-d for `dinosiglip-224px`).
"""

from __future__ import annotations

import torch
from torch import nn

from openfly_agent.model.config import (
    DINOSIGLIP_TIMM_IDS,
    DinoSiglipVisionConfig,
    TinyVitVisionConfig,
    VisionConfig,
)
from openfly_agent.model.vision.conv import IMAGENET_MEAN, IMAGENET_STD  # conv.py registers `tiny-cnn`

SIGLIP_MEAN = (0.5, 0.5, 0.5)
SIGLIP_STD = (0.5, 0.5, 0.5)
SIGLIP_MLP_RATIO = 3.7362  # So400m's MLP width / embedding width, kept for the tiny SigLIP-style ViT


def build_featurizers(cfg: VisionConfig, prune: bool = True) -> tuple[nn.Module, nn.Module]:
    """The (DINO-style, SigLIP-style) timm ViTs of a ViT variant (its registered backbone's `featurizers`), never
    with pretrained weights.

    Args:
        cfg: vision section of the model config (`tiny` or `dinosiglip-224px`).
        prune: drop the last block, the final norm and the pooling head (what the backbone uses); False gives
            the full architectures, whose extra keys the OpenVLA loader recognises as unused.
    """
    dino, siglip = type(cfg).builder().featurizers(cfg)
    if prune:
        for vit in (dino, siglip):
            vit.prune_intermediate_layers(indices=[len(vit.blocks) - 2], prune_norm=True, prune_head=True)
    return dino, siglip


def _normalise(pixels: torch.Tensor, mean: tuple[float, ...], std: tuple[float, ...], dtype) -> torch.Tensor:
    x = pixels.float() / 255.0  # (N, 3, H, W) in [0, 1]
    mean_t = torch.tensor(mean, device=pixels.device).view(1, 3, 1, 1)
    std_t = torch.tensor(std, device=pixels.device).view(1, 3, 1, 1)
    return ((x - mean_t) / std_t).to(dtype)


class FusedVisionBackbone(nn.Module):
    """`featurizer` (DINOv2-style) + `fused_featurizer` (SigLIP-style); normalises uint8 pixels itself. Each ViT
    variant subclasses it with its `featurizers`.

    Args:
        cfg: vision section of the model config.
    """

    def __init__(self, cfg: VisionConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.featurizer, self.fused_featurizer = build_featurizers(cfg)

    @staticmethod
    def featurizers(cfg: VisionConfig) -> tuple[nn.Module, nn.Module]:
        """The variant's two ViTs, whole (`build_featurizers` prunes them)."""
        raise NotImplementedError

    @property
    def feature_dim(self) -> int:
        """Width of the fused features."""
        return self.cfg.feature_dim

    def _check(self, pixels: torch.Tensor) -> None:
        size = self.cfg.image_size
        if pixels.dtype != torch.uint8 or pixels.ndim != 4 or tuple(pixels.shape[1:]) != (3, size, size):
            raise ValueError(
                f"vision backbone expects uint8 RGB pixels of shape (N, 3, {size}, {size}); got "
                f"{pixels.dtype} {tuple(pixels.shape)} (agent.processor.image resizes a frame to it)"
            )

    def forward_with_cls(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fused patch features and the DINO CLS token (the released model's history summary).

        Args:
            pixels: (N, 3, H, W) uint8 RGB.

        Returns:
            (N, P, D_dino + D_siglip) patch features and (N, D_dino) DINO CLS features.
        """
        self._check(pixels)
        dtype = self.featurizer.patch_embed.proj.weight.dtype
        dino = self.featurizer.forward_features(_normalise(pixels, IMAGENET_MEAN, IMAGENET_STD, dtype))
        siglip = self.fused_featurizer.forward_features(_normalise(pixels, SIGLIP_MEAN, SIGLIP_STD, dtype))
        # (N, prefix + P, D): prefix = CLS + 4 registers for DINOv2, none for SigLIP
        dino_patches = dino[:, self.featurizer.num_prefix_tokens :]
        siglip_patches = siglip[:, self.fused_featurizer.num_prefix_tokens :]
        return torch.cat([dino_patches, siglip_patches], dim=-1), dino[:, 0]  # (N, P, D), (N, D_dino)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) uint8 -> (N, P, D) fused patch features of the second-to-last blocks."""
        return self.forward_with_cls(pixels)[0]

    def set_grad_checkpointing(self, enable: bool = True) -> None:
        """Activation checkpointing of both ViTs (timm)."""
        self.featurizer.set_grad_checkpointing(enable)
        self.fused_featurizer.set_grad_checkpointing(enable)

    @property
    def dino_dim(self) -> int:
        """Width of the DINO-style featurizer (the CLS token's width)."""
        return self.cfg.featurizer_widths[0]


@DinoSiglipVisionConfig.register_builder
class DinoSiglipBackbone(FusedVisionBackbone):
    """`dinosiglip-224px`: the real timm architectures (weights come from a checkpoint, never downloaded)."""

    @staticmethod
    def featurizers(cfg: VisionConfig) -> tuple[nn.Module, nn.Module]:
        import timm

        dino = timm.create_model(DINOSIGLIP_TIMM_IDS[0], pretrained=False, num_classes=0, img_size=224)
        siglip = timm.create_model(DINOSIGLIP_TIMM_IDS[1], pretrained=False, num_classes=0, img_size=224)
        return dino, siglip


@TinyVitVisionConfig.register_builder
class TinyVitBackbone(FusedVisionBackbone):
    """`tiny`: two small ViTs of the dinosiglip structure (registers and LayerScale / a MAP head)."""

    @staticmethod
    def featurizers(cfg: VisionConfig) -> tuple[nn.Module, nn.Module]:
        from timm.models.vision_transformer import VisionTransformer

        common = {
            "img_size": cfg.image_size,
            "patch_size": cfg.patch_size,
            "depth": cfg.depth,
            "num_classes": 0,
        }
        dino = VisionTransformer(
            embed_dim=cfg.width,
            num_heads=cfg.num_heads,
            init_values=1e-5,
            reg_tokens=4,
            no_embed_class=True,
            **common,
        )
        siglip = VisionTransformer(
            embed_dim=cfg.fused_width,
            num_heads=cfg.num_heads,
            mlp_ratio=SIGLIP_MLP_RATIO,
            class_token=False,
            global_pool="map",
            **common,
        )
        return dino, siglip


def build_vision_backbone(cfg: VisionConfig) -> nn.Module:
    """The backbone of a vision section, as its variant registered it: `ConvVisionBackbone` (`tiny-cnn`),
    `TinyVitBackbone` (`tiny`) or `DinoSiglipBackbone` (`dinosiglip-224px`)."""
    return cfg.build()


def encode_frames(
    backbone: nn.Module,
    pixels: torch.Tensor,
    frame_index: torch.Tensor | None = None,
) -> torch.Tensor:
    """(F, 3, H, W) uint8 -> (N, P, D_v) features of `backbone`; sequence i reads frame `frame_index[i]` (default
    i)."""
    features = backbone(pixels)  # (F, P, D_v)
    return features if frame_index is None else features[frame_index.to(features.device)]

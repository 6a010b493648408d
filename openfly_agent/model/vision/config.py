"""The vision section of the model config: one registered choice per backbone (`type:` in YAML,
`--model.vision.type=` on the command line), each with only its own fields; stdlib and draccus only.

Part of the typed model config (model/config.py, which re-exports these names).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from draccus import ChoiceRegistry

from openfly_agent.model.config_checks import check_choice, check_positive
from openfly_agent.model.config_choice import BuiltChoice

VISION_DINOSIGLIP_224 = "dinosiglip-224px"
VISION_TINY = "tiny"  # two small ViTs of the dinosiglip structure
VISION_TINY_CNN = "tiny-cnn"  # a small ResNet with the same token grid (model/vision/conv.py)
VISION_PRESETS = (VISION_DINOSIGLIP_224, VISION_TINY, VISION_TINY_CNN)
CNN_STRIDE = 16  # tiny-cnn: pixels per token side (the ResNet's output stride)
# The real timm architectures of the `dinosiglip-224px` preset (weights come from a checkpoint, never
# downloaded).
DINOSIGLIP_TIMM_IDS = ("vit_large_patch14_reg4_dinov2", "vit_so400m_patch14_siglip_224")
DINOSIGLIP_WIDTHS = (1024, 1152)

RESIZE_MODES = ("bicubic", "area")
CNN_STEM_RESNET = "resnet"  # tiny-cnn stem: timm's 7 x 7 stride-2 conv (64 ch) + 3 x 3 stride-2 max pool
CNN_STEM_PATCH4 = "patch4"  # tiny-cnn stem: one 4 x 4 stride-4 conv (64 channels), no pool: no full-res maps
CNN_STEMS = (CNN_STEM_RESNET, CNN_STEM_PATCH4)


@dataclass
class VisionConfig(BuiltChoice, ChoiceRegistry):
    """The vision backbone: uint8 frames -> one feature vector per cell of a square token grid.

    `type` picks the backbone: `tiny-cnn` (the CPU default, `TinyCnnVisionConfig`, built by `ConvVisionBackbone`),
    `tiny` (`TinyVitVisionConfig`, `TinyVitBackbone`) or `dinosiglip-224px` (`DinoSiglipVisionConfig`,
    `DinoSiglipBackbone`); `build()` gives the backbone (model/config_choice.py). `image_size` and `resize` also
    define the image preprocessing (the processor's image transform).
    """

    image_size: int = 128  # square input side in pixels; must be a multiple of patch_size
    patch_size: int = CNN_STRIDE  # pixels per token side (tiny-cnn: the ResNet's stride, 16)
    resize: str = "bicubic"  # image transform interpolation: bicubic (PIL, as OpenVLA) | area (OpenCV)

    @classmethod
    def default_choice_name(cls) -> str:
        return VISION_TINY_CNN

    @property
    def type(self) -> str:
        """The registered name of this backbone (`tiny-cnn`, `tiny`, `dinosiglip-224px`)."""
        return self.get_choice_name(type(self))

    def __post_init__(self) -> None:
        check_choice("vision", "resize", self.resize, RESIZE_MODES)
        for name in ("image_size", "patch_size"):
            check_positive("vision", name, getattr(self, name))
        if self.image_size % self.patch_size:
            raise ValueError(
                f"vision.image_size={self.image_size} must be a multiple of "
                f"vision.patch_size={self.patch_size}"
            )

    @property
    def grid_side(self) -> int:
        """Patches per image side (16 for 224 px / patch 14)."""
        return self.image_size // self.patch_size

    @property
    def num_patches(self) -> int:
        """P, patch tokens per frame."""
        return self.grid_side**2

    @property
    def featurizer_widths(self) -> tuple[int, int]:
        """Widths of (featurizer, fused_featurizer)."""
        raise NotImplementedError

    @property
    def feature_dim(self) -> int:
        """Fused per-patch feature width (2176 for dinosiglip-224px)."""
        return sum(self.featurizer_widths)


@VisionConfig.register_subclass(VISION_TINY_CNN)
@dataclass
class TinyCnnVisionConfig(VisionConfig):
    """`tiny-cnn`: a small timm ResNet of output stride 16: a 128 px frame gives an 8 x 8 token grid, into the same
    projector and LLM as the ViTs' patches (model/vision/conv.py)."""

    cnn_channels: list[int] = field(
        default_factory=lambda: [32, 64, 96, 128]
    )  # widths of the 4 ResNet stages
    # add to each token a projection of its cell's colour statistics (mean and spread of the normalised RGB over
    # the cell, the means of its 2 x 2 quarters): the trained ResNet's features keep a landmark's type but not its
    # colour (docs/experiments/2026-11-24-grounding-levers.md, "Which landmark the head picks")
    cnn_colour_stats: bool = False
    # the ResNet's stem (CNN_STEMS), both stride 4 with 64 channels into the first stage: `resnet` (timm's, whose
    # 64-channel maps at half the input resolution took about 30 % of a CPU training step) or `patch4` (a 4 x 4
    # stride-4 convolution, as a ViT's patch embedding; docs/experiments/2026-11-26-speed-levers.md, "The patch stem")
    cnn_stem: str = CNN_STEM_RESNET

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("vision", "cnn_stem", self.cnn_stem, CNN_STEMS)
        if self.patch_size != CNN_STRIDE:
            raise ValueError(
                f"vision.type=tiny-cnn has a stride of {CNN_STRIDE}: set patch_size={CNN_STRIDE}"
            )
        if len(self.cnn_channels) != 4 or min(self.cnn_channels) <= 0:
            raise ValueError(f"vision.cnn_channels={self.cnn_channels} must be 4 positive stage widths")

    @property
    def featurizer_widths(self) -> tuple[int, int]:
        """The ResNet's last stage; no fused featurizer (width 0)."""
        return (self.cnn_channels[-1], 0)


@VisionConfig.register_subclass(VISION_TINY)
@dataclass
class TinyVitVisionConfig(VisionConfig):
    """`tiny`: two small ViTs of the dinosiglip structure, read at the output of the second-to-last block,
    without the final norm."""

    width: int = 96  # DINO-style ViT width
    fused_width: int = 128  # SigLIP-style ViT width
    depth: int = 3  # blocks per ViT (features come from block depth - 2)
    num_heads: int = 4

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("width", "fused_width", "depth", "num_heads"):
            check_positive("vision", name, getattr(self, name))
        if self.depth < 2:
            raise ValueError(f"vision.depth={self.depth}: need >= 2 blocks (features of the second-to-last)")
        for name in ("width", "fused_width"):
            if getattr(self, name) % self.num_heads:
                raise ValueError(
                    f"vision.{name}={getattr(self, name)} must be divisible by num_heads={self.num_heads}"
                )

    @property
    def featurizer_widths(self) -> tuple[int, int]:
        return (self.width, self.fused_width)


@VisionConfig.register_subclass(VISION_DINOSIGLIP_224)
@dataclass
class DinoSiglipVisionConfig(VisionConfig):
    """`dinosiglip-224px`: the real timm architectures (224 px, patch 14, 256 patches, 1024 + 1152 = 2176-d),
    read at the output of the second-to-last block, without the final norm."""

    image_size: int = 224
    patch_size: int = 14

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.image_size, self.patch_size) != (224, 14):
            raise ValueError(
                f"vision.type=dinosiglip-224px needs image_size=224 and patch_size=14 "
                f"(got {self.image_size}, {self.patch_size}); use type=tiny for other sizes"
            )

    @property
    def featurizer_widths(self) -> tuple[int, int]:
        return DINOSIGLIP_WIDTHS

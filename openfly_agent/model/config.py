"""Typed configuration of the OpenFly-Agent model: one nested dataclass per component, plus the presets.

Leaf module (stdlib, draccus and constants only) so run configs can compose it without importing torch. The
vision backbone, the LLM, the grounding head, the memory encoding and the action head are registered choices
(draccus `ChoiceRegistry`): the section's `type` names the variant, and each variant has only its own fields. A
variant builds its own module (`build`, registered by the module that implements it: model/config_choice.py).

The sections of the vision backbone, the grounding head and the language side (LLM, prompt, action head) are
defined beside their modules (model/vision/config.py, model/grounding/config.py, model/language/config.py); this
module holds the memory sections, `ModelConfig` that composes them all, the presets and the LoRA settings, and
re-exports the sections' names, so that `openfly_agent.model.config` is the one place to import them from.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from draccus import ChoiceRegistry

from openfly_agent.model.config_checks import check_positive
from openfly_agent.model.config_choice import BuiltChoice
from openfly_agent.model.grounding.config import (
    GROUNDING_BOX,
    GROUNDING_CELLS,
    GROUNDING_NONE,
    BoxGroundingConfig,
    CellGroundingConfig,
    GroundingConfig,
    GroundingHeadConfig,
    NoGroundingConfig,
)
from openfly_agent.model.language.config import (
    DECODE_EXACT,
    DECODE_NEAREST,
    DECODE_RULES,
    HEAD_DISCRETE,
    HEAD_OPENVLA_BINS,
    LLAMA2_7B_ARCH,
    LLAMA2_PADDED_VOCAB,
    LLAMA2_TOKENIZER_VOCAB,
    LLM_LLAMA2_7B,
    NUM_ACTION_SLOTS,
    ActionHeadConfig,
    BinsActionHeadConfig,
    DiscreteActionHeadConfig,
    Llama2LLMConfig,
    LLMConfig,
    PromptConfig,
    TinyLLMConfig,
)
from openfly_agent.model.vision.config import (
    CNN_STEM_PATCH4,
    CNN_STEMS,
    CNN_STRIDE,
    DINOSIGLIP_TIMM_IDS,
    DINOSIGLIP_WIDTHS,
    RESIZE_MODES,
    VISION_DINOSIGLIP_224,
    VISION_PRESETS,
    VISION_TINY,
    VISION_TINY_CNN,
    DinoSiglipVisionConfig,
    TinyCnnVisionConfig,
    TinyVitVisionConfig,
    VisionConfig,
)

ENCODING_KEYFRAMES = "keyframes"  # keyframe sets merged, grid-pooled (model/memory/keyframe_memory.py)
ENCODING_OPENVLA_HISTORY = "openvla_history"  # the released model's history (model/memory/history_memory.py)


@dataclass
class KeyframeConfig:
    """Keyframe sets: each motion change point c gives frames c - radius .. c + radius, kept by box area."""

    theta: float = 0.25  # keep a frame when its landmark box covers >= theta of the image
    radius: int = 2  # frames before and after the change point
    merge_forward: bool = True  # forward 1 / 8 / 9 count as one motion class

    def __post_init__(self) -> None:
        if not 0.0 <= self.theta <= 1.0:
            raise ValueError(f"keyframes.theta={self.theta} must be in [0, 1] (a fraction of the image area)")
        if self.radius < 0:
            raise ValueError(f"keyframes.radius={self.radius} must be >= 0")

    @property
    def set_size(self) -> int:
        """S, the most frames one keyframe set can hold."""
        return 2 * self.radius + 1


@dataclass
class MergingConfig:
    """Visual token merging into the largest-box reference frame of a keyframe set."""

    enabled: bool = True
    threshold: float | None = 0.9  # merge a token when its best cosine similarity is >= threshold
    top_r: int | None = None  # and/or keep only the r most similar tokens per comparative frame

    def __post_init__(self) -> None:
        if self.enabled and self.threshold is None and self.top_r is None:
            raise ValueError("merging.enabled needs merging.threshold or merging.top_r (or both)")
        if self.threshold is not None and not -1.0 <= self.threshold <= 1.0:
            raise ValueError(f"merging.threshold={self.threshold} must be a cosine similarity in [-1, 1]")
        if self.top_r is not None and self.top_r < 0:
            raise ValueError(f"merging.top_r={self.top_r} must be >= 0")


@dataclass
class MemoryEncodingConfig(BuiltChoice, ChoiceRegistry):
    """How past frames become memory tokens: `type` picks `keyframes` (the default, `KeyframeEncodingConfig`: the
    last K keyframe sets, each merged into its largest-box frame, grid-pooled, projected) or `openvla_history`
    (`HistoryEncodingConfig`: the released model's one token per past frame). `build(model_cfg, selector)` gives
    the encoding (model/factory.py, model/memory/encoding.py)."""

    @classmethod
    def default_choice_name(cls) -> str:
        return ENCODING_KEYFRAMES

    @property
    def type(self) -> str:
        """The registered name of this encoding (`keyframes`, `openvla_history`)."""
        return self.get_choice_name(type(self))

    def tokens_per_set(self, grid_side: int, grid: int) -> int:
        """Memory tokens of one keyframe set (or history frame) on a grid_side x grid_side patch grid pooled by
        `grid`."""
        raise NotImplementedError

    def check_model(self, model: ModelConfig) -> None:
        """Refuse the other sections' settings this encoding cannot run with (ValueError)."""


@MemoryEncodingConfig.register_subclass(ENCODING_KEYFRAMES)
@dataclass
class KeyframeEncodingConfig(MemoryEncodingConfig):
    """`keyframes`: (grid_side / g)^2 tokens per keyframe set (the `merging` and `keyframes` sections)."""

    def tokens_per_set(self, grid_side: int, grid: int) -> int:
        return (grid_side // grid) ** 2


@MemoryEncodingConfig.register_subclass(ENCODING_OPENVLA_HISTORY)
@dataclass
class HistoryEncodingConfig(MemoryEncodingConfig):
    """`openvla_history`: the released IPEC-COMMUNITY/openfly-agent-7b's forward, one token per past frame (DINO CLS
    ++ SigLIP patches pooled over the whole grid)."""

    def tokens_per_set(self, grid_side: int, grid: int) -> int:
        return 1

    def check_model(self, model: ModelConfig) -> None:
        name = f"memory.encoding.type={ENCODING_OPENVLA_HISTORY}"
        if model.action_head.type != HEAD_OPENVLA_BINS:
            raise ValueError(f"{name} reproduces the released model: set action_head.type=openvla_bins")
        side = model.vision.grid_side
        if model.memory.grid != side:
            raise ValueError(f"{name} summarises each history frame in one token: set memory.grid={side}")
        if model.vision.type == VISION_TINY_CNN:
            raise ValueError(f"{name} reproduces the released ViT backbone: not vision.type=tiny-cnn")


@dataclass
class MemoryConfig:
    """FIFO memory of K keyframe sets (or past frames), each grid-pooled to `memory_tokens_per_set` tokens."""

    capacity: int = 2  # K; 0 = current frame only
    grid: int = 8  # g, pooling window in patches (the paper: 16 on the 16x16 grid of 224 px)
    encoding: MemoryEncodingConfig = field(default_factory=KeyframeEncodingConfig)

    def __post_init__(self) -> None:
        if self.capacity < 0:
            raise ValueError(f"memory.capacity={self.capacity} must be >= 0")
        check_positive("memory", "grid", self.grid)


@dataclass
class ModelConfig:
    """Everything that defines an OpenFly-Agent network (serialised inside config.json)."""

    vision: VisionConfig = field(default_factory=TinyCnnVisionConfig)
    llm: LLMConfig = field(default_factory=TinyLLMConfig)
    prompt: PromptConfig = field(default_factory=PromptConfig)
    grounding: GroundingConfig = field(default_factory=CellGroundingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    merging: MergingConfig = field(default_factory=MergingConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    action_head: ActionHeadConfig = field(default_factory=DiscreteActionHeadConfig)

    def __post_init__(self) -> None:
        side = self.vision.grid_side
        if side % self.memory.grid:
            raise ValueError(
                f"memory.grid={self.memory.grid} must divide the patch grid side {side} "
                f"(vision.image_size / vision.patch_size); e.g. one of {_divisors(side)}"
            )
        self.memory.encoding.check_model(self)
        if self.uses_box_token and not self.grounding.has_head:
            raise ValueError(
                "action_head.box_token reads the action at the grounding head's box: it needs a head "
                f"(grounding.type={GROUNDING_CELLS} or {GROUNDING_BOX}; or set action_head.box_token=false)"
            )
        vocab = self.llm.vocab_size
        if (
            vocab is not None
            and self.action_head.vocab_end is not None
            and self.action_head.vocab_end > vocab
        ):
            raise ValueError(
                f"action_head.vocab_end={self.action_head.vocab_end} exceeds llm.vocab_size={vocab}"
            )

    @property
    def memory_tokens_per_set(self) -> int:
        """(grid_side / g)^2 tokens per keyframe set (1 at 224 px, g = 16); `openvla_history`: 1 per past frame."""
        return self.memory.encoding.tokens_per_set(self.vision.grid_side, self.memory.grid)

    @property
    def uses_box_token(self) -> bool:
        """`action_head.box_token` of the discrete head, with None resolved: on when there is a grounding head;
        never with the bins head."""
        head = self.action_head
        if not isinstance(head, DiscreteActionHeadConfig):
            return False
        return self.grounding.has_head if head.box_token is None else head.box_token

    def visual_tokens_per_step(self, num_memory_sets: int | None = None) -> int:
        """P current-frame tokens + memory tokens (K full sets by default): 256 + 2 = 258 for 7B."""
        sets = self.memory.capacity if num_memory_sets is None else num_memory_sets
        return self.vision.num_patches + sets * self.memory_tokens_per_set


def _divisors(n: int) -> list[int]:
    return [d for d in range(1, n + 1) if n % d == 0]


def tiny_config(**overrides) -> ModelConfig:
    """CPU preset (= the dataclass defaults): a small ResNet at 128 px (8x8 tokens), a 2-layer Llama of width 128,
    the grounding head with cell scoring, the box token before the action, K = 2, g = 8 (1 token per keyframe
    set)."""
    return dataclasses.replace(ModelConfig(), **overrides)


def openfly_7b_config(**overrides) -> ModelConfig:
    """The paper's model: dinosiglip-224px + llama2-7b, K = 2, g = 16 (256 + 2 visual tokens per step)."""
    cfg = ModelConfig(
        vision=DinoSiglipVisionConfig(),
        llm=Llama2LLMConfig(
            vocab_size=LLAMA2_PADDED_VOCAB,
            pad_token_id=LLAMA2_TOKENIZER_VOCAB,
            length_groups=1,
        ),
        prompt=PromptConfig(),
        action_head=DiscreteActionHeadConfig(vocab_end=LLAMA2_TOKENIZER_VOCAB, box_token=False),
        grounding=BoxGroundingConfig(dim=256, num_heads=8),
        memory=MemoryConfig(capacity=2, grid=16),
    )
    return dataclasses.replace(cfg, **overrides)


def openvla_compat_7b_config(**overrides) -> ModelConfig:
    """The released IPEC-COMMUNITY/openfly-agent-7b forward: 2 history frames, raw prompt, 8-dim bins."""
    cfg = openfly_7b_config(
        memory=MemoryConfig(capacity=2, grid=16, encoding=HistoryEncodingConfig()),
        prompt=PromptConfig(template="{instruction}", suffix_token_id=29871),
        action_head=BinsActionHeadConfig(
            vocab_end=LLAMA2_TOKENIZER_VOCAB, decode_rule=DECODE_EXACT, unnorm_key="vlnv1"
        ),
    )
    return dataclasses.replace(cfg, **overrides)


MODEL_PRESETS = {
    "tiny": tiny_config,
    "openfly-7b": openfly_7b_config,
    "openvla-compat-7b": openvla_compat_7b_config,
}


def make_model_config(preset: str, **overrides) -> ModelConfig:
    """A preset by name (`tiny`, `openfly-7b`, `openvla-compat-7b`), with top-level sections replaced."""
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; choose one of {sorted(MODEL_PRESETS)}")
    return MODEL_PRESETS[preset](**overrides)


__all__ = [  # the sections' names are re-exported: model.config is the one place to import config from
    "CNN_STEMS",
    "CNN_STEM_PATCH4",
    "CNN_STRIDE",
    "DECODE_EXACT",
    "DECODE_NEAREST",
    "DECODE_RULES",
    "HEAD_DISCRETE",
    "HEAD_OPENVLA_BINS",
    "LLAMA2_7B_ARCH",
    "LLM_LLAMA2_7B",
    "NUM_ACTION_SLOTS",
    "DINOSIGLIP_TIMM_IDS",
    "DINOSIGLIP_WIDTHS",
    "GROUNDING_BOX",
    "GROUNDING_CELLS",
    "GROUNDING_NONE",
    "RESIZE_MODES",
    "VISION_DINOSIGLIP_224",
    "VISION_PRESETS",
    "VISION_TINY",
    "VISION_TINY_CNN",
    "ActionHeadConfig",
    "BinsActionHeadConfig",
    "BoxGroundingConfig",
    "CellGroundingConfig",
    "DinoSiglipVisionConfig",
    "DiscreteActionHeadConfig",
    "GroundingConfig",
    "GroundingHeadConfig",
    "HistoryEncodingConfig",
    "KeyframeConfig",
    "KeyframeEncodingConfig",
    "LLMConfig",
    "Llama2LLMConfig",
    "MemoryConfig",
    "MemoryEncodingConfig",
    "MergingConfig",
    "ModelConfig",
    "NoGroundingConfig",
    "PromptConfig",
    "TinyCnnVisionConfig",
    "TinyLLMConfig",
    "TinyVitVisionConfig",
    "VisionConfig",
    "make_model_config",
]


@dataclass
class LoraSettings:
    """LoRA on the LLM through peft (OpenVLA's finetune.py defaults: r 32, alpha 16, all linear layers)."""

    rank: int = 32
    alpha: int = 16
    dropout: float = 0.0
    target_modules: str = "all-linear"  # peft's shorthand (every Linear but lm_head) or comma-separated names
    init: str = "gaussian"  # peft init_lora_weights

    def __post_init__(self) -> None:
        check_positive("lora", "rank", self.rank)
        check_positive("lora", "alpha", self.alpha)
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"lora.dropout={self.dropout} must be in [0, 1)")

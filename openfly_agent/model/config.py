"""Typed configuration of the OpenFly-Agent model: one nested dataclass per component, plus the presets.

Leaf module (stdlib, draccus and constants only) so run configs can compose it without importing torch. The
vision backbone, the grounding head and the action head are registered choices (draccus `ChoiceRegistry`): the
section's `type` names the variant, and each variant has only its own fields.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from draccus import ChoiceRegistry

from openfly_agent.model.config_checks import check_choice, check_positive, fill_tiny_fields
from openfly_agent.model.grounding.config import (
    GROUNDING_BOX,
    GROUNDING_CELLS,
    BoxGroundingConfig,
    CellGroundingConfig,
    GroundingConfig,
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

MODE_OPENFLY = "openfly"
MODE_OPENVLA_COMPAT = "openvla_compat"
MODES = (MODE_OPENFLY, MODE_OPENVLA_COMPAT)

LLM_LLAMA2_7B = "llama2-7b"
LLM_TINY = "tiny"
LLM_PRESETS = (LLM_LLAMA2_7B, LLM_TINY)
# transformers' attention back-ends: sdpa (torch's scaled_dot_product_attention, the default), eager (the
# explicit softmax), flash_attention_2 (needs the flash-attn wheel and a GPU); tests/model/test_model_attention.py
# checks that eager and sdpa give the same actions
ATTN_IMPLEMENTATIONS = ("sdpa", "eager", "flash_attention_2")
# SentencePiece vocab of Llama-2; OpenVLA adds <PAD> = 32000 and pads the embedding rows to 32064.
LLAMA2_TOKENIZER_VOCAB = 32000
LLAMA2_PADDED_VOCAB = 32064

HEAD_DISCRETE = "discrete"
HEAD_OPENVLA_BINS = "openvla_bins"
ACTION_HEADS = (HEAD_DISCRETE, HEAD_OPENVLA_BINS)
DECODE_EXACT = "exact"
DECODE_NEAREST = "nearest"
DECODE_RULES = (DECODE_EXACT, DECODE_NEAREST)
NUM_ACTION_SLOTS = 256  # both heads use the last 256 ids below `action_head.vocab_end`

# Llama-2-7B's architecture (meta-llama/Llama-2-7b-hf config.json); weights always come from a checkpoint.
LLAMA2_7B_ARCH = {
    "hidden_size": 4096,
    "intermediate_size": 11008,
    "num_hidden_layers": 32,
    "num_attention_heads": 32,
    "rms_norm_eps": 1e-5,
}
# Sizes of the `tiny` LLM preset, taken by the tiny-only fields left at None (rejected by the 7B preset when set).
TINY_LLM = {"hidden_size": 128, "num_layers": 2, "num_heads": 4, "intermediate_size": 344}


@dataclass
class ProjectorConfig:
    """Fused GELU MLP: fc1 (D_v -> ratio * D_v), GELU, fc2 (-> D_llm), GELU, fc3 (D_llm -> D_llm)."""

    hidden_ratio: int = 4

    def __post_init__(self) -> None:
        check_positive("projector", "hidden_ratio", self.hidden_ratio)


@dataclass
class LLMConfig:
    """Causal LM (transformers Llama). `llama2-7b` fixes the architecture (`LLAMA2_7B_ARCH`); `tiny` reads the
    four size fields below (None takes `TINY_LLM`).

    `vocab_size` = embedding rows. None derives it: 32064 for llama2-7b (OpenVLA's padded vocab); for tiny the
    tokenizer length + 256 reserved action ids (needs the tokenizer when the model is built).
    """

    preset: str = LLM_TINY
    tokenizer_path: str | None = None  # local folder with the tokenizer files (never downloaded)
    vocab_size: int | None = None
    hidden_size: int | None = None  # tiny only
    num_layers: int | None = None  # tiny only
    num_heads: int | None = None  # tiny only
    intermediate_size: int | None = None  # tiny only
    max_length: int = 2048
    attn_implementation: str = "sdpa"  # one of ATTN_IMPLEMENTATIONS (passed to transformers)
    # training forward: the decoder stack runs on up to this many groups of rows of similar length, each cut to
    # its longest row (model/language/length_groups.py; same loss, fewer padded positions); 1 runs the padded batch in one
    # call (the 7B presets)
    length_groups: int = 3
    # Special token ids (taken from the tokenizer when the model is built with one).
    bos_token_id: int = 1
    eos_token_id: int = 2
    pad_token_id: int | None = None

    def __post_init__(self) -> None:
        check_choice("llm", "preset", self.preset, LLM_PRESETS)
        check_choice("llm", "attn_implementation", self.attn_implementation, ATTN_IMPLEMENTATIONS)
        fill_tiny_fields("llm", self, self.preset == LLM_TINY, TINY_LLM)
        if self.vocab_size is not None and self.vocab_size <= NUM_ACTION_SLOTS:
            raise ValueError(
                f"llm.vocab_size={self.vocab_size} must exceed the {NUM_ACTION_SLOTS} action ids"
            )
        check_positive("llm", "max_length", self.max_length)
        check_positive("llm", "length_groups", self.length_groups)
        if self.preset != LLM_TINY:
            return
        for name in TINY_LLM:
            check_positive("llm", name, getattr(self, name))
        if self.hidden_size % self.num_heads:
            raise ValueError(
                f"llm.hidden_size={self.hidden_size} must be divisible by llm.num_heads={self.num_heads}"
            )

    @property
    def resolved_hidden_size(self) -> int:
        """LLM width of the chosen preset."""
        return LLAMA2_7B_ARCH["hidden_size"] if self.preset == LLM_LLAMA2_7B else self.hidden_size


@dataclass
class PromptConfig:
    """How an instruction becomes the text after the visual tokens."""

    template: str = "What action should the drone take to {instruction}?"
    # the text of a grounding-stage sample (a referring expression, no action)
    grounding_template: str = "Where is {expression}?"
    lowercase: bool = False
    # Token appended after the prompt at inference (OpenVLA's predict_action appends 29871 '▁' for Llama-2).
    suffix_token_id: int | None = None

    def __post_init__(self) -> None:
        if "{instruction}" not in self.template:
            raise ValueError(
                f"prompt.template={self.template!r} must contain the placeholder {{instruction}}"
            )
        if "{expression}" not in self.grounding_template:
            raise ValueError(
                f"prompt.grounding_template={self.grounding_template!r} must contain the placeholder {{expression}}"
            )


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
class MemoryConfig:
    """FIFO memory of K keyframe sets, each grid-pooled to (grid_side / g)^2 tokens."""

    capacity: int = 2  # K; 0 = current frame only
    grid: int = 8  # g, pooling window in patches (the paper: 16 on the 16x16 grid of 224 px)

    def __post_init__(self) -> None:
        if self.capacity < 0:
            raise ValueError(f"memory.capacity={self.capacity} must be >= 0")
        check_positive("memory", "grid", self.grid)


@dataclass
class ActionHeadConfig(ChoiceRegistry):
    """Action tokens: `type` picks `discrete` (one token per step, `DiscreteActionHeadConfig`, the default) or
    `openvla_bins` (8 dims x 256 bins, OpenVLA format, `BinsActionHeadConfig`).

    Both use the 256 ids just below `vocab_end` (None = llm vocab size). The discrete head maps action a to id
    `vocab_end - 256 + a`; the bins head maps bin b (1..256) to `vocab_end - b` as OpenVLA does.
    """

    n_bins: int = NUM_ACTION_SLOTS
    vocab_end: int | None = None

    @classmethod
    def default_choice_name(cls) -> str:
        return HEAD_DISCRETE

    @property
    def type(self) -> str:
        """The registered name of this head (`discrete`, `openvla_bins`)."""
        return self.get_choice_name(type(self))

    def __post_init__(self) -> None:
        if self.n_bins != NUM_ACTION_SLOTS:
            raise ValueError(f"action_head.n_bins={self.n_bins}: only {NUM_ACTION_SLOTS} bins are supported")
        if self.vocab_end is not None and self.vocab_end < NUM_ACTION_SLOTS:
            raise ValueError(f"action_head.vocab_end={self.vocab_end} must be >= {NUM_ACTION_SLOTS}")


@ActionHeadConfig.register_subclass(HEAD_DISCRETE)
@dataclass
class DiscreteActionHeadConfig(ActionHeadConfig):
    """`discrete`: one token per step.

    `box_token` (None: on exactly when the grounding head is enabled; the 7B presets set it off to keep the
    paper's layout): the grounding head's box of the target, embedded as one more input token after the prompt,
    is what the action is read at, so the action is conditioned on where the target is (a grounded chain of
    thought, as ECoT's bounding boxes before the action). Training embeds the ground-truth box jittered by
    `box_token_jitter`; inference the predicted one (docs/ARCHITECTURE.md).
    """

    # the action is read at an embedded-box token after the prompt (None: when the grounding head is enabled)
    box_token: bool | None = None
    box_token_jitter: float = 0.05  # std of the noise on the training box (centre; log size x 2)
    # weight of the STOP-labelled steps in the action cross-entropy (1.0: plain cross-entropy)
    stop_loss_weight: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.box_token_jitter < 0:
            raise ValueError(f"action_head.box_token_jitter={self.box_token_jitter} must be >= 0")
        if self.stop_loss_weight <= 0:
            raise ValueError(f"action_head.stop_loss_weight={self.stop_loss_weight} must be > 0")


@ActionHeadConfig.register_subclass(HEAD_OPENVLA_BINS)
@dataclass
class BinsActionHeadConfig(ActionHeadConfig):
    """`openvla_bins`: 8 action dims x 256 bins, decoded greedily and un-normalised with a norm-stats profile."""

    decode_rule: str = DECODE_EXACT  # exact (official: exact match else STOP) | nearest
    unnorm_key: str | None = None  # which entry of norm_stats un-normalises the bins (None: the only one)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("action_head", "decode_rule", self.decode_rule, DECODE_RULES)


@dataclass
class ModelConfig:
    """Everything that defines an OpenFly-Agent network (serialised inside config.json)."""

    mode: str = MODE_OPENFLY  # openfly | openvla_compat (the released checkpoint's forward)
    vision: VisionConfig = field(default_factory=TinyCnnVisionConfig)
    projector: ProjectorConfig = field(default_factory=ProjectorConfig)
    llm: LLMConfig = field(default_factory=LLMConfig)
    prompt: PromptConfig = field(default_factory=PromptConfig)
    grounding: GroundingConfig = field(default_factory=CellGroundingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    merging: MergingConfig = field(default_factory=MergingConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    action_head: ActionHeadConfig = field(default_factory=DiscreteActionHeadConfig)

    def __post_init__(self) -> None:
        check_choice("model", "mode", self.mode, MODES)
        side = self.vision.grid_side
        if side % self.memory.grid:
            raise ValueError(
                f"memory.grid={self.memory.grid} must divide the patch grid side {side} "
                f"(vision.image_size / vision.patch_size); e.g. one of {_divisors(side)}"
            )
        if self.mode == MODE_OPENVLA_COMPAT and self.action_head.type != HEAD_OPENVLA_BINS:
            raise ValueError(
                "mode=openvla_compat reproduces the released model: set action_head.type=openvla_bins"
            )
        if self.mode == MODE_OPENVLA_COMPAT and self.memory.grid != side:
            raise ValueError(
                f"mode=openvla_compat summarises each history frame in one token: set memory.grid={side}"
            )
        if self.uses_box_token and not self.grounding.enabled:
            raise ValueError(
                "action_head.box_token reads the action at the grounding head's box: it needs "
                "grounding.enabled=true (or set action_head.box_token=false)"
            )
        if self.mode == MODE_OPENVLA_COMPAT and self.vision.type == VISION_TINY_CNN:
            raise ValueError(
                "mode=openvla_compat reproduces the released ViT backbone: not vision.type=tiny-cnn"
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
        """(grid_side / g)^2 tokens per keyframe set (1 at 224 px, g = 16); compat: 1 per history frame."""
        if self.mode == MODE_OPENVLA_COMPAT:
            return 1
        return (self.vision.grid_side // self.memory.grid) ** 2

    @property
    def uses_box_token(self) -> bool:
        """`action_head.box_token` of the discrete head, with None resolved: on when grounding is enabled; never
        with the bins head."""
        head = self.action_head
        if not isinstance(head, DiscreteActionHeadConfig):
            return False
        return self.grounding.enabled if head.box_token is None else head.box_token

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
        llm=LLMConfig(
            preset=LLM_LLAMA2_7B,
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
        mode=MODE_OPENVLA_COMPAT,
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


__all__ = [  # the vision section's names are re-exported: model.config is the one place to import config from
    "CNN_STEMS",
    "CNN_STEM_PATCH4",
    "CNN_STRIDE",
    "DINOSIGLIP_TIMM_IDS",
    "DINOSIGLIP_WIDTHS",
    "GROUNDING_BOX",
    "GROUNDING_CELLS",
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
    "KeyframeConfig",
    "LLMConfig",
    "MemoryConfig",
    "MergingConfig",
    "ModelConfig",
    "ProjectorConfig",
    "PromptConfig",
    "TinyCnnVisionConfig",
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

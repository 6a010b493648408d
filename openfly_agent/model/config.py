"""Typed configuration of the OpenFly-Agent model: one nested dataclass per component, plus the presets.

Leaf module (stdlib + constants only) so run configs can compose it without importing torch.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

MODE_OPENFLY = "openfly"
MODE_OPENVLA_COMPAT = "openvla_compat"
MODES = (MODE_OPENFLY, MODE_OPENVLA_COMPAT)

VISION_DINOSIGLIP_224 = "dinosiglip-224px"
VISION_TINY = "tiny"  # two small ViTs of the dinosiglip structure
VISION_TINY_CNN = "tiny-cnn"  # a small ResNet with the same token grid (model/conv_vision.py)
VISION_PRESETS = (VISION_DINOSIGLIP_224, VISION_TINY, VISION_TINY_CNN)
CNN_STRIDE = 16  # tiny-cnn: pixels per token side (the ResNet's output stride)
# The real timm architectures of the `dinosiglip-224px` preset (weights come from a checkpoint, never
# downloaded).
DINOSIGLIP_TIMM_IDS = ("vit_large_patch14_reg4_dinov2", "vit_so400m_patch14_siglip_224")
DINOSIGLIP_WIDTHS = (1024, 1152)

LLM_LLAMA2_7B = "llama2-7b"
LLM_TINY = "tiny"
LLM_PRESETS = (LLM_LLAMA2_7B, LLM_TINY)
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

RESIZE_MODES = ("bicubic", "area")

# Llama-2-7B's architecture (meta-llama/Llama-2-7b-hf config.json); weights always come from a checkpoint.
LLAMA2_7B_ARCH = {
    "hidden_size": 4096,
    "intermediate_size": 11008,
    "num_hidden_layers": 32,
    "num_attention_heads": 32,
    "rms_norm_eps": 1e-5,
}
# Sizes of the `tiny` presets, taken by the tiny-only fields left at None (ignored by the 7B presets, which
# reject them when set).
TINY_VISION = {"width": 96, "fused_width": 128, "depth": 3, "num_heads": 4}
TINY_CNN_VISION = {"cnn_channels": [32, 64, 96, 128], "cnn_stem_width": 16}
TINY_LLM = {"hidden_size": 128, "num_layers": 2, "num_heads": 4, "intermediate_size": 344}


def _check_choice(section: str, name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{section}.{name}={value!r} is not supported; use one of {list(choices)}")


def _check_positive(section: str, name: str, value: float) -> None:
    if value <= 0:
        raise ValueError(f"{section}.{name} must be > 0, got {value}")


def _fill_tiny_fields(section: str, cfg, is_tiny: bool, defaults: dict[str, int]) -> None:
    """Tiny preset: fill the unset tiny-only fields with `defaults`. Other presets: reject any that is set."""
    for name, default in defaults.items():
        value = getattr(cfg, name)
        if is_tiny and value is None:
            setattr(cfg, name, default)
        elif not is_tiny and value is not None:
            raise ValueError(
                f"{section}.{name}={value} is read by the tiny preset only; {section}.preset={cfg.preset} fixes "
                f"the architecture, so remove {section}.{name} (or use {section}.preset=tiny)"
            )


@dataclass
class VisionConfig:
    """The vision backbone: uint8 frames -> one feature vector per cell of a square token grid.

    `dinosiglip-224px` builds the real timm architectures (224 px, patch 14, 256 patches,
    1024 + 1152 = 2176-d); `tiny` builds two small ViTs of the same structure from `image_size`,
    `patch_size`, `width`, `fused_width`, `depth` and `num_heads` (None takes `TINY_VISION`). Both read the
    output of the second-to-last block, without the final norm. `tiny-cnn` (the CPU default) is a small timm
    ResNet of output stride 16 with `cnn_channels` stage widths (None takes `TINY_CNN_VISION`): a 128 px frame
    gives the same 8 x 8 token grid, into the same projector and LLM (model/conv_vision.py). `image_size` and
    `resize` also define the image preprocessing (the processor's image transform).
    """

    preset: str = VISION_TINY_CNN
    image_size: int = 128  # square input side in pixels; must be a multiple of patch_size
    patch_size: int = CNN_STRIDE  # pixels per token side (tiny-cnn: the ResNet's stride, 16)
    width: int | None = None  # tiny only: DINO-style ViT width
    fused_width: int | None = None  # tiny only: SigLIP-style ViT width
    depth: int | None = None  # tiny only: blocks per ViT (features come from block depth - 2)
    num_heads: int | None = None  # tiny only
    cnn_channels: list[int] | None = (
        None  # tiny-cnn only: widths of the 4 ResNet stages (the last = features)
    )
    cnn_stem_width: int | None = None  # tiny-cnn only: channels of the stem convolution
    resize: str = "bicubic"  # image transform interpolation: bicubic (PIL, as OpenVLA) | area (OpenCV)

    def __post_init__(self) -> None:
        _check_choice("vision", "preset", self.preset, VISION_PRESETS)
        _check_choice("vision", "resize", self.resize, RESIZE_MODES)
        _fill_tiny_fields("vision", self, self.preset == VISION_TINY, TINY_VISION)
        _fill_tiny_fields("vision", self, self.preset == VISION_TINY_CNN, TINY_CNN_VISION)
        if self.preset == VISION_DINOSIGLIP_224 and (self.image_size, self.patch_size) != (224, 14):
            raise ValueError(
                f"vision.preset=dinosiglip-224px needs image_size=224 and patch_size=14 "
                f"(got {self.image_size}, {self.patch_size}); use preset=tiny for other sizes"
            )
        for name in ("image_size", "patch_size"):
            _check_positive("vision", name, getattr(self, name))
        if self.image_size % self.patch_size:
            raise ValueError(
                f"vision.image_size={self.image_size} must be a multiple of "
                f"vision.patch_size={self.patch_size}"
            )
        if self.preset == VISION_TINY_CNN:
            if self.patch_size != CNN_STRIDE:
                raise ValueError(
                    f"vision.preset=tiny-cnn has a stride of {CNN_STRIDE}: set patch_size={CNN_STRIDE}"
                )
            if len(self.cnn_channels) != 4 or min(self.cnn_channels) <= 0 or self.cnn_stem_width <= 0:
                raise ValueError(
                    f"vision.cnn_channels={self.cnn_channels} must be 4 positive stage widths and "
                    f"vision.cnn_stem_width={self.cnn_stem_width} positive"
                )
        if self.preset != VISION_TINY:
            return
        for name in TINY_VISION:
            _check_positive("vision", name, getattr(self, name))
        if self.depth < 2:
            raise ValueError(f"vision.depth={self.depth}: need >= 2 blocks (features of the second-to-last)")
        for name in ("width", "fused_width"):
            if getattr(self, name) % self.num_heads:
                raise ValueError(
                    f"vision.{name}={getattr(self, name)} must be divisible by num_heads={self.num_heads}"
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
        """Widths of (featurizer, fused_featurizer); tiny-cnn has no fused featurizer (width 0)."""
        if self.preset == VISION_TINY_CNN:
            return (self.cnn_channels[-1], 0)
        return DINOSIGLIP_WIDTHS if self.preset == VISION_DINOSIGLIP_224 else (self.width, self.fused_width)

    @property
    def feature_dim(self) -> int:
        """Fused per-patch feature width (2176 for dinosiglip-224px)."""
        return sum(self.featurizer_widths)


@dataclass
class ProjectorConfig:
    """Fused GELU MLP: fc1 (D_v -> ratio * D_v), GELU, fc2 (-> D_llm), GELU, fc3 (D_llm -> D_llm)."""

    hidden_ratio: int = 4

    def __post_init__(self) -> None:
        _check_positive("projector", "hidden_ratio", self.hidden_ratio)


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
    attn_implementation: str = "sdpa"  # sdpa | eager | flash_attention_2 (passed to transformers)
    # Special token ids (taken from the tokenizer when the model is built with one).
    bos_token_id: int = 1
    eos_token_id: int = 2
    pad_token_id: int | None = None

    def __post_init__(self) -> None:
        _check_choice("llm", "preset", self.preset, LLM_PRESETS)
        _fill_tiny_fields("llm", self, self.preset == LLM_TINY, TINY_LLM)
        if self.vocab_size is not None and self.vocab_size <= NUM_ACTION_SLOTS:
            raise ValueError(
                f"llm.vocab_size={self.vocab_size} must exceed the {NUM_ACTION_SLOTS} action ids"
            )
        _check_positive("llm", "max_length", self.max_length)
        if self.preset != LLM_TINY:
            return
        for name in TINY_LLM:
            _check_positive("llm", name, getattr(self, name))
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
class GroundingConfig:
    """Landmark grounding head: learned queries cross-attend to the LLM hidden states and regress a box.

    `cells` (the tiny preset) adds per-cell scoring of the current frame: the query starts from the last prompt
    token, FiLM-scores every cell, the box centre is the softmax-weighted cell centre plus an offset, and
    `cell_weight` x the cross-entropy of the cell holding the box centre joins the loss (model/grounding.py).
    """

    enabled: bool = True
    num_layers: int = 3
    num_queries: int = 1
    dim: int = 128  # 256 in the 7B preset
    num_heads: int = 4  # 8 in the 7B preset
    loss_weight: float = 1.0  # weight of the grounding loss in the total loss
    l1_weight: float = 1.0  # grounding loss = GIoU + l1_weight * L1 (visible boxes) + visibility_weight * BCE
    visibility_weight: float = (
        0.5  # 0 disables the visibility logit's loss (predicted boxes then always count)
    )
    cells: bool = True  # per-cell scoring and box centre (False: the paper's box regression, the 7B presets)
    cell_weight: float = 1.0  # weight of the cell cross-entropy (with `cells`)

    def __post_init__(self) -> None:
        for name in ("num_layers", "num_queries", "dim", "num_heads"):
            _check_positive("grounding", name, getattr(self, name))
        if self.dim % self.num_heads:
            raise ValueError(
                f"grounding.dim={self.dim} must be divisible by grounding.num_heads={self.num_heads}"
            )
        for name in ("loss_weight", "l1_weight", "visibility_weight", "cell_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"grounding.{name} must be >= 0, got {getattr(self, name)}")


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
        _check_positive("memory", "grid", self.grid)


@dataclass
class ActionHeadConfig:
    """Action tokens: `discrete` (one token per step) or `openvla_bins` (8 dims x 256 bins, OpenVLA format).

    Both use the 256 ids just below `vocab_end` (None = llm vocab size). The discrete head maps action a to id
    `vocab_end - 256 + a`; the bins head maps bin b (1..256) to `vocab_end - b` as OpenVLA does.

    `box_token` (None: on exactly when the head is discrete and the grounding head enabled; the 7B presets set
    it off to keep the paper's layout): the grounding head's box of the target, embedded as one more
    input token after the prompt, is what the action is read at, so the action is conditioned on where the
    target is (a grounded chain of thought, as ECoT's bounding boxes before the action). Training embeds the
    ground-truth box jittered by `box_token_jitter`; inference the predicted one (docs/ARCHITECTURE.md).
    """

    type: str = HEAD_DISCRETE
    n_bins: int = NUM_ACTION_SLOTS
    decode_rule: str = DECODE_EXACT  # openvla_bins: exact (official: exact match else STOP) | nearest
    unnorm_key: str | None = None  # which entry of norm_stats un-normalises the bins (None: the only one)
    vocab_end: int | None = None
    # the action is read at an embedded-box token after the prompt (None: when discrete with grounding)
    box_token: bool | None = None
    box_token_jitter: float = 0.05  # std of the noise on the training box (centre; log size x 2)

    def __post_init__(self) -> None:
        _check_choice("action_head", "type", self.type, ACTION_HEADS)
        _check_choice("action_head", "decode_rule", self.decode_rule, DECODE_RULES)
        if self.n_bins != NUM_ACTION_SLOTS:
            raise ValueError(f"action_head.n_bins={self.n_bins}: only {NUM_ACTION_SLOTS} bins are supported")
        if self.vocab_end is not None and self.vocab_end < NUM_ACTION_SLOTS:
            raise ValueError(f"action_head.vocab_end={self.vocab_end} must be >= {NUM_ACTION_SLOTS}")
        if self.box_token_jitter < 0:
            raise ValueError(f"action_head.box_token_jitter={self.box_token_jitter} must be >= 0")


@dataclass
class ModelConfig:
    """Everything that defines an OpenFly-Agent network (serialised inside config.json)."""

    mode: str = MODE_OPENFLY  # openfly | openvla_compat (the released checkpoint's forward)
    vision: VisionConfig = field(default_factory=VisionConfig)
    projector: ProjectorConfig = field(default_factory=ProjectorConfig)
    llm: LLMConfig = field(default_factory=LLMConfig)
    prompt: PromptConfig = field(default_factory=PromptConfig)
    grounding: GroundingConfig = field(default_factory=GroundingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    merging: MergingConfig = field(default_factory=MergingConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    action_head: ActionHeadConfig = field(default_factory=ActionHeadConfig)

    def __post_init__(self) -> None:
        _check_choice("model", "mode", self.mode, MODES)
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
        if self.action_head.box_token and not self._box_token_possible:
            raise ValueError(
                "action_head.box_token reads the action at the grounding head's box: it needs "
                "action_head.type=discrete and grounding.enabled=true (or set action_head.box_token=false)"
            )
        if self.mode == MODE_OPENVLA_COMPAT and self.vision.preset == VISION_TINY_CNN:
            raise ValueError(
                "mode=openvla_compat reproduces the released ViT backbone: not vision.preset=tiny-cnn"
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
    def _box_token_possible(self) -> bool:
        return self.action_head.type == HEAD_DISCRETE and self.grounding.enabled

    @property
    def uses_box_token(self) -> bool:
        """`action_head.box_token`, with None resolved: on when the head is discrete and grounding enabled."""
        if self.action_head.box_token is None:
            return self._box_token_possible
        return self.action_head.box_token

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
        vision=VisionConfig(preset=VISION_DINOSIGLIP_224, image_size=224, patch_size=14),
        llm=LLMConfig(
            preset=LLM_LLAMA2_7B, vocab_size=LLAMA2_PADDED_VOCAB, pad_token_id=LLAMA2_TOKENIZER_VOCAB
        ),
        prompt=PromptConfig(),
        action_head=ActionHeadConfig(vocab_end=LLAMA2_TOKENIZER_VOCAB, box_token=False),
        grounding=GroundingConfig(dim=256, num_heads=8, cells=False),
        memory=MemoryConfig(capacity=2, grid=16),
    )
    return dataclasses.replace(cfg, **overrides)


def openvla_compat_7b_config(**overrides) -> ModelConfig:
    """The released IPEC-COMMUNITY/openfly-agent-7b forward: 2 history frames, raw prompt, 8-dim bins."""
    cfg = openfly_7b_config(
        mode=MODE_OPENVLA_COMPAT,
        prompt=PromptConfig(template="{instruction}", suffix_token_id=29871),
        action_head=ActionHeadConfig(
            type=HEAD_OPENVLA_BINS,
            vocab_end=LLAMA2_TOKENIZER_VOCAB,
            decode_rule=DECODE_EXACT,
            unnorm_key="vlnv1",
            box_token=False,
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


def config_to_dict(cfg: ModelConfig) -> dict:
    """Plain JSON-friendly dict of a ModelConfig (nested sections as dicts)."""
    return dataclasses.asdict(cfg)


def config_from_dict(data: dict) -> ModelConfig:
    """Inverse of `config_to_dict`; unknown keys raise with the section and key named."""
    sections = {f.name: f for f in dataclasses.fields(ModelConfig)}
    kwargs = {}
    for key, value in data.items():
        if key not in sections:
            raise ValueError(f"model config: unknown key {key!r}; known: {sorted(sections)}")
        section_type = _SECTION_TYPES.get(key)
        if section_type is None:
            kwargs[key] = value
            continue
        known = {f.name for f in dataclasses.fields(section_type)}
        unknown = set(value) - known
        if unknown:
            raise ValueError(
                f"model config: unknown key(s) {sorted(unknown)} in section {key!r}; known: {sorted(known)}"
            )
        kwargs[key] = section_type(**value)
    return ModelConfig(**kwargs)


_SECTION_TYPES = {
    "vision": VisionConfig,
    "projector": ProjectorConfig,
    "llm": LLMConfig,
    "prompt": PromptConfig,
    "grounding": GroundingConfig,
    "keyframes": KeyframeConfig,
    "merging": MergingConfig,
    "memory": MemoryConfig,
    "action_head": ActionHeadConfig,
}

__all__ = [
    "ActionHeadConfig",
    "GroundingConfig",
    "KeyframeConfig",
    "LLMConfig",
    "MemoryConfig",
    "MergingConfig",
    "ModelConfig",
    "ProjectorConfig",
    "PromptConfig",
    "VisionConfig",
    "config_from_dict",
    "config_to_dict",
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
        _check_positive("lora", "rank", self.rank)
        _check_positive("lora", "alpha", self.alpha)
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"lora.dropout={self.dropout} must be in [0, 1)")

"""Typed configuration of the language side of the model: the LLM (a registered choice: `tiny` or `llama2-7b`),
the prompt around the instruction, and the action head (a registered choice: `discrete` or `openvla_bins`) whose
tokens the LLM writes.

Leaf module (stdlib, draccus and constants only), composed by model/config.py::ModelConfig, which re-exports its
names: import them from `openfly_agent.model.config`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from draccus import ChoiceRegistry

from openfly_agent.model.config_checks import check_choice, check_positive
from openfly_agent.model.config_choice import BuiltChoice

LLM_LLAMA2_7B = "llama2-7b"
LLM_TINY = "tiny"
# transformers' attention back-ends: sdpa (torch's scaled_dot_product_attention, the default), eager (the
# explicit softmax), flash_attention_2 (needs the flash-attn wheel and a GPU); tests/model/test_model_attention.py
# checks that eager and sdpa give the same actions
ATTN_IMPLEMENTATIONS = ("sdpa", "eager", "flash_attention_2")
# SentencePiece vocab of Llama-2; OpenVLA adds <PAD> = 32000 and pads the embedding rows to 32064.
LLAMA2_TOKENIZER_VOCAB = 32000
LLAMA2_PADDED_VOCAB = 32064

HEAD_DISCRETE = "discrete"
HEAD_OPENVLA_BINS = "openvla_bins"
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


@dataclass
class LLMConfig(BuiltChoice, ChoiceRegistry):
    """Causal LM (transformers Llama): `type` picks `tiny` (the default, `TinyLLMConfig`, with its own sizes) or
    `llama2-7b` (`Llama2LLMConfig`, Llama-2-7B's architecture `LLAMA2_7B_ARCH`). `build(vocab_size)` gives the
    freshly initialised LM (model/language/llm.py).

    `vocab_size` = embedding rows. None derives it (`default_vocab_size`): 32064 for llama2-7b (OpenVLA's padded
    vocab); for tiny the tokenizer length + 256 reserved action ids (needs the tokenizer when the model is built).
    """

    tokenizer_path: str | None = None  # local folder with the tokenizer files (never downloaded)
    vocab_size: int | None = None
    max_length: int = 2048
    attn_implementation: str = "sdpa"  # one of ATTN_IMPLEMENTATIONS (passed to transformers)
    # training forward: the decoder stack runs on up to this many groups of rows of similar length, each cut to
    # its longest row (model/layout.py, `run_in_length_groups`; same loss, fewer padded positions); 1 runs the padded batch in one
    # call (the 7B presets)
    length_groups: int = 3
    # Special token ids (taken from the tokenizer when the model is built with one).
    bos_token_id: int = 1
    eos_token_id: int = 2
    pad_token_id: int | None = None

    # whether training makes this LLM's tokenizer when none is given (the tiny BPE tokenizer; docs/TRAINING.md)
    trains_own_tokenizer: ClassVar[bool] = False

    @classmethod
    def default_choice_name(cls) -> str:
        return LLM_TINY

    @property
    def type(self) -> str:
        """The registered name of this LLM (`tiny`, `llama2-7b`)."""
        return self.get_choice_name(type(self))

    def __post_init__(self) -> None:
        check_choice("llm", "attn_implementation", self.attn_implementation, ATTN_IMPLEMENTATIONS)
        if self.vocab_size is not None and self.vocab_size <= NUM_ACTION_SLOTS:
            raise ValueError(
                f"llm.vocab_size={self.vocab_size} must exceed the {NUM_ACTION_SLOTS} action ids"
            )
        check_positive("llm", "max_length", self.max_length)
        check_positive("llm", "length_groups", self.length_groups)

    @property
    def architecture(self) -> dict[str, int | float]:
        """The Llama sizes: hidden_size, intermediate_size, num_hidden_layers, num_attention_heads, rms_norm_eps."""
        raise NotImplementedError

    @property
    def hidden_size(self) -> int:
        """LLM width."""
        return self.architecture["hidden_size"]

    def default_vocab_size(self, tokenizer_length: int | None) -> int:
        """The embedding rows when `vocab_size` is None, for a tokenizer of `tokenizer_length` tokens (None: no
        tokenizer)."""
        raise NotImplementedError


@LLMConfig.register_subclass(LLM_TINY)
@dataclass
class TinyLLMConfig(LLMConfig):
    """`tiny`: a small Llama of the sizes below, whose vocabulary is the trained BPE tokenizer + 256 action ids."""

    hidden_size: int = 128  # width of the hidden states (and of the visual tokens the projector makes)
    num_layers: int = 2  # decoder layers
    num_heads: int = 4  # attention heads; must divide hidden_size
    intermediate_size: int = 344  # width of each layer's MLP

    trains_own_tokenizer: ClassVar[bool] = True

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("hidden_size", "num_layers", "num_heads", "intermediate_size"):
            check_positive("llm", name, getattr(self, name))
        if self.hidden_size % self.num_heads:
            raise ValueError(
                f"llm.hidden_size={self.hidden_size} must be divisible by llm.num_heads={self.num_heads}"
            )

    @property
    def architecture(self) -> dict[str, int | float]:
        return {
            "hidden_size": self.hidden_size,
            "intermediate_size": self.intermediate_size,
            "num_hidden_layers": self.num_layers,
            "num_attention_heads": self.num_heads,
            "rms_norm_eps": 1e-5,
        }

    def default_vocab_size(self, tokenizer_length: int | None) -> int:
        if tokenizer_length is None:
            raise ValueError(
                "the tiny LLM sizes its vocabulary from the tokenizer: pass tokenizer= or set llm.vocab_size"
            )
        return tokenizer_length + NUM_ACTION_SLOTS


@LLMConfig.register_subclass(LLM_LLAMA2_7B)
@dataclass
class Llama2LLMConfig(LLMConfig):
    """`llama2-7b`: Llama-2-7B's architecture (`LLAMA2_7B_ARCH`); the weights always come from a checkpoint and
    the tokenizer from `tokenizer_path`."""

    @property
    def architecture(self) -> dict[str, int | float]:
        return dict(LLAMA2_7B_ARCH)

    def default_vocab_size(self, tokenizer_length: int | None) -> int:
        return LLAMA2_PADDED_VOCAB


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
class ActionHeadConfig(ChoiceRegistry):
    """Action tokens: `type` picks `discrete` (one token per step, `DiscreteActionHeadConfig`, the default) or
    `openvla_bins` (8 dims x 256 bins, OpenVLA format, `BinsActionHeadConfig`).

    Both use the 256 ids just below `vocab_end` (None = llm vocab size). The discrete head maps action a to id
    `vocab_end - 256 + a`; the bins head maps bin b (1..256) to `vocab_end - b` as OpenVLA does.
    """

    vocab_end: int | None = None

    @classmethod
    def default_choice_name(cls) -> str:
        return HEAD_DISCRETE

    @property
    def type(self) -> str:
        """The registered name of this head (`discrete`, `openvla_bins`)."""
        return self.get_choice_name(type(self))

    def __post_init__(self) -> None:
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

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.box_token_jitter < 0:
            raise ValueError(f"action_head.box_token_jitter={self.box_token_jitter} must be >= 0")


@ActionHeadConfig.register_subclass(HEAD_OPENVLA_BINS)
@dataclass
class BinsActionHeadConfig(ActionHeadConfig):
    """`openvla_bins`: 8 action dims x 256 bins, decoded greedily and un-normalised with a norm-stats profile."""

    decode_rule: str = DECODE_EXACT  # exact (official: exact match else STOP) | nearest
    unnorm_key: str | None = None  # which entry of norm_stats un-normalises the bins (None: the only one)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("action_head", "decode_rule", self.decode_rule, DECODE_RULES)

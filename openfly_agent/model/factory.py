"""Builders from the config: vocabulary resolution from a tokenizer, the action tokenizer, the memory encoding (each
encoding registers its builder with its variant: model/memory/keyframe_memory.py, history_memory.py)."""

from __future__ import annotations

import dataclasses
import logging

from openfly_agent.model.config import (
    DECODE_EXACT,
    HEAD_DISCRETE,
    NUM_ACTION_SLOTS,
    BinsActionHeadConfig,
    ModelConfig,
)
from openfly_agent.model.language.action_tokenizer import ActionTokenizer, select_action_stats
from openfly_agent.model.memory import history_memory, keyframe_memory  # noqa: F401 (register their builders)
from openfly_agent.model.memory.encoding import MemoryEncoding
from openfly_agent.model.memory.keyframes import KeyframeSelector

logger = logging.getLogger(__name__)


def action_stats_of(cfg: ModelConfig, norm_stats: dict | None) -> dict | None:
    """The `action` norm stats the head un-normalises with: profile `action_head.unnorm_key` (bins head only)."""
    if cfg.action_head.type == HEAD_DISCRETE:
        return None
    return select_action_stats(norm_stats, cfg.action_head.unnorm_key)


def make_action_tokenizer(cfg: ModelConfig, norm_stats: dict | None) -> ActionTokenizer:
    """The action tokenizer of a (resolved) model config; bins heads take their profile of `norm_stats`."""
    head = cfg.action_head
    return ActionTokenizer(
        head=head.type,
        vocab_end=head.vocab_end or cfg.llm.vocab_size,
        eos_token_id=cfg.llm.eos_token_id,
        action_stats=action_stats_of(cfg, norm_stats),
        decode_rule=head.decode_rule if isinstance(head, BinsActionHeadConfig) else DECODE_EXACT,
    )


def resolve_vocabulary(cfg: ModelConfig, tokenizer) -> ModelConfig:
    """Fill llm.vocab_size (the LLM variant's `default_vocab_size` when None), special ids and
    action_head.vocab_end from the tokenizer."""
    llm = cfg.llm
    vocab = llm.vocab_size
    if vocab is None:
        vocab = llm.default_vocab_size(None if tokenizer is None else len(tokenizer))
    ids = {}
    if tokenizer is not None:
        if len(tokenizer) > vocab:
            raise ValueError(f"tokenizer has {len(tokenizer)} tokens but llm.vocab_size is {vocab}")
        for name in ("bos_token_id", "eos_token_id", "pad_token_id"):
            if getattr(tokenizer, name, None) is not None:
                ids[name] = int(getattr(tokenizer, name))
    llm = dataclasses.replace(llm, vocab_size=vocab, **ids)
    head = cfg.action_head
    if head.vocab_end is None:
        head = dataclasses.replace(head, vocab_end=vocab)
    if tokenizer is not None and len(tokenizer) > head.vocab_end - NUM_ACTION_SLOTS:
        logger.info(
            "action ids %d..%d overlap the tokenizer's vocabulary (OpenVLA's convention for Llama-2)",
            head.vocab_end - NUM_ACTION_SLOTS,
            head.vocab_end - 1,
        )
    return dataclasses.replace(cfg, llm=llm, action_head=head)


def make_memory_encoding(cfg: ModelConfig, selector: KeyframeSelector) -> MemoryEncoding:
    """The memory encoding `memory.encoding.type` names, as its variant registered it: the keyframe memory read
    through `selector` (`KeyframeMemory`, `keyframes`) or the OpenVLA-compatible history (`HistoryMemory`,
    `openvla_history`)."""
    return cfg.memory.encoding.build(cfg, selector)

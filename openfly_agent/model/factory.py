"""Builders from the config: vocabulary resolution from a tokenizer, the action tokenizer, the memory encoding."""

from __future__ import annotations

import dataclasses
import logging

from openfly_agent.model.config import (
    DECODE_EXACT,
    HEAD_DISCRETE,
    LLAMA2_PADDED_VOCAB,
    LLM_LLAMA2_7B,
    MODE_OPENVLA_COMPAT,
    NUM_ACTION_SLOTS,
    BinsActionHeadConfig,
    ModelConfig,
)
from openfly_agent.model.language.action_tokenizer import ActionTokenizer, select_action_stats
from openfly_agent.model.memory.encoding import MemoryEncoding
from openfly_agent.model.memory.history_memory import HistoryMemory
from openfly_agent.model.memory.keyframe_memory import KeyframeMemory
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
    """Fill llm.vocab_size, special ids and action_head.vocab_end from the preset / tokenizer."""
    llm = cfg.llm
    vocab = llm.vocab_size
    if vocab is None:
        if llm.preset == LLM_LLAMA2_7B:
            vocab = LLAMA2_PADDED_VOCAB
        elif tokenizer is None:
            raise ValueError(
                "the tiny LLM sizes its vocabulary from the tokenizer: pass tokenizer= or set llm.vocab_size"
            )
        else:
            vocab = len(tokenizer) + NUM_ACTION_SLOTS
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
    """The memory encoding of `cfg.mode`, chosen once: the OpenVLA-compatible history (`openvla_compat`) or the
    keyframe memory read through `selector` (every other mode)."""
    if cfg.mode == MODE_OPENVLA_COMPAT:
        return HistoryMemory(cfg.memory.capacity, cfg.memory.grid, cfg.llm.resolved_hidden_size)
    return KeyframeMemory(cfg, selector)

"""The causal LM (transformers Llama) under OpenVLA's key names: `language_model.model.*`, `.lm_head`."""

from __future__ import annotations

import functools
import inspect

from torch import nn

from openfly_agent.model.config import Llama2LLMConfig, LLMConfig, TinyLLMConfig


def llama_config(cfg: LLMConfig, vocab_size: int):
    """The `transformers.LlamaConfig` of an LLM section (its variant's `architecture`; vocab_size resolved by the
    caller)."""
    from transformers import LlamaConfig

    config = LlamaConfig(
        vocab_size=vocab_size,
        max_position_embeddings=cfg.max_length,
        bos_token_id=cfg.bos_token_id,
        eos_token_id=cfg.eos_token_id,
        pad_token_id=cfg.pad_token_id,
        tie_word_embeddings=False,
        **cfg.architecture,
    )
    config._attn_implementation = cfg.attn_implementation
    return config


def build_language_model(cfg: LLMConfig, vocab_size: int) -> nn.Module:
    """The LM of an LLM section, as its variant registered it (`tiny` and `llama2-7b`: `llama_causal_lm`)."""
    return cfg.build(vocab_size)


@TinyLLMConfig.register_builder
@Llama2LLMConfig.register_builder
def llama_causal_lm(cfg: LLMConfig, vocab_size: int) -> nn.Module:
    """A freshly initialised `LlamaForCausalLM` of the variant's architecture (no download, ever)."""
    from transformers import LlamaForCausalLM

    return LlamaForCausalLM(llama_config(cfg, vocab_size))


@functools.cache
def cache_keyword(decoder_class: type) -> str:
    """The decoder's keyword for the KV cache: `cache`, or `past_key_values` before transformers renamed it (read
    once per class: every decoding step passes it)."""
    return "cache" if "cache" in inspect.signature(decoder_class.forward).parameters else "past_key_values"

"""The causal LM (transformers Llama) under OpenVLA's key names: `language_model.model.*`, `.lm_head`."""

from __future__ import annotations

import functools
import inspect

from torch import nn

from openfly_agent.model.config import LLAMA2_7B_ARCH, LLM_LLAMA2_7B, LLMConfig


def llama_config(cfg: LLMConfig, vocab_size: int):
    """The `transformers.LlamaConfig` of an LLM section (vocab_size resolved by the caller)."""
    from transformers import LlamaConfig

    if cfg.preset == LLM_LLAMA2_7B:
        arch = dict(LLAMA2_7B_ARCH)
    else:
        arch = {
            "hidden_size": cfg.hidden_size,
            "intermediate_size": cfg.intermediate_size,
            "num_hidden_layers": cfg.num_layers,
            "num_attention_heads": cfg.num_heads,
            "rms_norm_eps": 1e-5,
        }
    config = LlamaConfig(
        vocab_size=vocab_size,
        max_position_embeddings=cfg.max_length,
        bos_token_id=cfg.bos_token_id,
        eos_token_id=cfg.eos_token_id,
        pad_token_id=cfg.pad_token_id,
        tie_word_embeddings=False,
        **arch,
    )
    config._attn_implementation = cfg.attn_implementation
    return config


def build_language_model(cfg: LLMConfig, vocab_size: int) -> nn.Module:
    """A freshly initialised `LlamaForCausalLM` of the preset's architecture (no download, ever)."""
    from transformers import LlamaForCausalLM

    return LlamaForCausalLM(llama_config(cfg, vocab_size))


def unwrap_causal_lm(language_model: nn.Module) -> nn.Module:
    """The underlying `LlamaForCausalLM`, also when peft wrapped it for LoRA (layers are patched in place)."""
    get_base = getattr(language_model, "get_base_model", None)
    return get_base() if callable(get_base) else language_model


@functools.cache
def cache_keyword(decoder_class: type) -> str:
    """The decoder's keyword for the KV cache: `cache`, or `past_key_values` before transformers renamed it (read
    once per class: every decoding step passes it)."""
    return "cache" if "cache" in inspect.signature(decoder_class.forward).parameters else "past_key_values"

"""The Llama LLM, the text and action tokenizers, sequence layout, cached decoding and LoRA."""

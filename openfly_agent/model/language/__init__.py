"""The Llama LLM, the text and action tokenizers, the LLM and prompt config, and LoRA."""

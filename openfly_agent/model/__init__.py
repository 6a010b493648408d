"""Level-1 model: vision backbone, projector, LLM, grounding head, keyframes, merging, memory, action tokenizer, agent."""

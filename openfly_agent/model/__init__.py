"""Level-1 model: vision, projector, LLM, grounding, keyframes, merging, memory, actions, agent."""

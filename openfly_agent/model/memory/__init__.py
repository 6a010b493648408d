"""The keyframe memory: keyframe selection, visual token merging, the memory bank and its encoding."""

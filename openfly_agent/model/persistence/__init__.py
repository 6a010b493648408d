"""Checkpoint folders: reading, OpenVLA weights, LoRA checkpoints, remote-code files."""

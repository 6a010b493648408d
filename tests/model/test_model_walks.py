"""How far the two walks reach (docs/ARCHITECTURE.md, "How far the two walks reach"): the files of the package one
training micro-batch (`OpenFlyAgent.forward`) and one closed-loop step (`AgentSession.predict_step`) enter, counted
with `sys.setprofile`, stay within the bounds issue 46 set (half of the 24 and 20 it counted)."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import openfly_agent

PACKAGE = str(Path(openfly_agent.__file__).resolve().parent) + "/"
MAX_TRAINING_FILES = 12
MAX_INFERENCE_FILES = 10
INSTRUCTIONS = [
    "Fly forward to the red skyscraper.",
    "Ascend above the white house and stop near the blue dome.",
]


def files_entered(step: Callable[[], object]) -> list[str]:
    """The package's files (relative to it) any Python call of `step()` runs in."""
    files = set()

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_filename.startswith(PACKAGE):
            files.add(frame.f_code.co_filename[len(PACKAGE) :])

    sys.setprofile(profile)
    try:
        step()
    finally:
        sys.setprofile(None)
    return sorted(files)


def _adopted_agent(make_agent, small_config):
    """The small agent with the adopted model's grounding (attributes, visual skip): every head runs."""
    grounding = dataclasses.replace(small_config().grounding, attribute_weight=1.0, visual_skip=True)
    return make_agent(seed=0, grounding=grounding)


def test_a_training_micro_batch_enters_at_most_12_files(make_agent, make_batch, small_config):
    agent = _adopted_agent(make_agent, small_config).train()
    batch = make_batch(agent, batch_size=2)
    files = files_entered(lambda: agent(batch))
    assert "model/agent.py" in files and "model/network.py" in files  # the profiler saw the step
    assert len(files) <= MAX_TRAINING_FILES, f"{len(files)} files: {files}"


def test_an_inference_step_enters_at_most_10_files(make_agent, small_config):
    agent = _adopted_agent(make_agent, small_config)
    size = agent.model_cfg.vision.image_size

    def observations(t: int) -> list[dict]:
        return [
            {
                "episode_id": f"e{i}",
                "instruction": INSTRUCTIONS[i],
                "rgb": np.full((size, size, 3), 10 * t + i, np.uint8),
                "pose": [float(t), 0.0, 0.0, 0.0],
            }
            for i in range(2)
        ]

    session = agent.new_session()
    with torch.no_grad():
        session.predict_step(observations(0))  # the first step starts the episodes; the second is a plain one
        files = files_entered(lambda: session.predict_step(observations(1)))
    assert "model/session.py" in files and "model/network.py" in files
    assert len(files) <= MAX_INFERENCE_FILES, f"{len(files)} files: {files}"

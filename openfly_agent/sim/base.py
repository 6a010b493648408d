"""The Simulator protocol every engine implements (embedded city, UnrealCV, AirSim, 3DGS HTTP).

A simulator is reset to an `EpisodeSpec` and stepped with OpenFly action ids; motion always goes
through `sim/dynamics.py`. Observations carry RGB, the pose and, where the engine can, landmark boxes
and depth. `VectorSimulator` steps many episodes in lockstep (see sim/vector.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from openfly_agent.utils.geometry import Pose


@dataclass(frozen=True)
class EpisodeSpec:
    """What a simulator needs to start an episode (built by eval/ or toolchain/ from dataset episodes)."""

    episode_id: str
    scene_id: str  # e.g. "embedded-17" or "env_airsim_16"
    start: Pose
    goal: np.ndarray | None = None  # (3,) metres; used for info only, metrics live in eval/
    pitch_deg: float = 0.0  # camera pitch: 0, or -45 for `high_*` categories
    landmark_id: str | None = None  # the target landmark, when known


# The frame of a simulator that does not render (one shared array: never write into it).
NO_FRAME = np.zeros((1, 1, 3), dtype=np.uint8)


@dataclass
class Observation:
    """One frame from a simulator."""

    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    pose: Pose
    boxes: dict[str, np.ndarray] | None = None  # landmark id -> (4,) (cx, cy, w, h) in [0, 1]
    depth: np.ndarray | None = None  # (H, W) float32 metres, where the engine provides it
    extra: dict = field(default_factory=dict)  # engine-specific extras (e.g. visible pixels per landmark)


@dataclass
class StepInfo:
    """What happened in one step."""

    action: int
    collided: bool = False  # the motion segment hit occupied space or the ground
    done: bool = False  # STOP, collision under an ending policy, or engine failure
    extra: dict = field(default_factory=dict)


@runtime_checkable
class Simulator(Protocol):
    """One episode at a time. Implementations must be usable as context managers via `close()`."""

    def reset(self, episode: EpisodeSpec) -> Observation: ...

    def step(self, action_id: int) -> tuple[Observation, StepInfo]: ...

    def close(self) -> None: ...

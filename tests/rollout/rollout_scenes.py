"""Dataset episodes in the embedded simulator's hand-built tower scene (tests/sim/scenes.py), for the runner tests."""

from __future__ import annotations

import dataclasses

import numpy as np
from data_factories import make_episode
from sim.scenes import tower_city

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.utils.geometry import Pose

SIZE = 32  # px: the frames are only looked at for the target box
TOWER = "b0000"  # the red tower's landmark id; its west face is at x = 90


def tower_episode(name: str, start: Pose, actions: list[int]) -> Episode:
    """An episode of the tower scene whose poses follow `actions` from `start`; the tower is its target."""
    poses = rollout_array(start, actions)[:-1]  # (T, 4): the pose at which each action is taken
    base = make_episode(f"test-tower/astar_data/low_short/{name}", actions)
    return dataclasses.replace(
        base, positions=poses[:, :3], yaws=poses[:, 3], pitch_deg=0.0, landmark_ids=[TOWER], goal=None
    )


def free_episodes(count: int) -> list[Episode]:
    """`count` episodes west of the tower, 20 m apart in y, facing north (away from it): nothing to hit."""
    return [
        tower_episode(
            f"free{i}", Pose(-100.0, -60.0 + 20.0 * i, 50.0, np.pi / 2), [C.ACTION_FORWARD, C.ACTION_STOP]
        )
        for i in range(count)
    ]


def tower_env(num_envs: int) -> VectorSimulator:
    """`num_envs` embedded simulators of the tower scene, collisions counted (never ending an episode)."""
    cfg = EmbeddedSimConfig(width=SIZE, height=SIZE, collision="count")
    return VectorSimulator.embedded(cfg, num_envs, cities=[tower_city()])

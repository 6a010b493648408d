"""Small builders shared by the evaluation tests: episodes that replay exactly, and a pose-only simulator.

`PoseSimulator` is a test double for the injected simulator: motion through `sim/dynamics.py`, collisions
against an `OccupancyGrid`, and a 4 x 4 frame whose pixels encode the pose (so a policy that looks at
frames sees different frames at different poses). The end-to-end tests use the embedded simulator.
"""

from __future__ import annotations

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.sim.base import EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.dynamics import rollout_array, step_motion
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.utils.geometry import Pose


def make_episode(
    episode_id: str, actions, start=(0.0, 0.0, 30.0, 0.0), scene_id: str = "scene-a", split=None
) -> Episode:
    """An episode whose positions are exactly the dynamics replay of `actions` (end them with STOP)."""
    poses = rollout_array(Pose(*start), actions)[:-1]  # (T, 4): the pose at which each action is taken
    return Episode(
        episode_id=episode_id,
        scene_id=scene_id,
        instruction=f"fly the route of {episode_id}",
        actions=np.asarray(actions),
        positions=poses[:, :3],
        yaws=poses[:, 3],
        frame_ids=[f"{episode_id}_{t}" for t in range(len(actions))],
        split=split,
        landmark_ids=[f"{scene_id}-lm0"],
    )


def wall_grid(x_from: float) -> OccupancyGrid:
    """Occupied for x >= `x_from` (a wall across the whole scene), free elsewhere; 1 m voxels."""
    bounds = SceneBounds(-200.0, 200.0, -200.0, 200.0, -10.0, 200.0)
    grid = OccupancyGrid.empty(bounds, 1.0)
    first = int(np.floor(x_from - bounds.xmin))
    grid.occupied[first:, :, :] = True
    return grid


class PoseSimulator:
    """Simulator protocol over the dynamics, with collisions from an occupancy grid (None = no obstacles)."""

    def __init__(self, grid: OccupancyGrid | None = None):
        self.grid = grid
        self.pose: Pose | None = None
        self.resets = 0

    def _obs(self) -> Observation:
        rgb = np.zeros((4, 4, 3), dtype=np.uint8)
        rgb[..., 0] = int(abs(self.pose.x)) % 256
        rgb[..., 1] = int(abs(self.pose.y)) % 256
        rgb[..., 2] = int(abs(self.pose.z)) % 256
        return Observation(rgb=rgb, pose=self.pose, boxes={})

    def reset(self, episode: EpisodeSpec) -> Observation:
        self.pose = episode.start
        self.resets += 1
        return self._obs()

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        motion = step_motion(self.pose, action_id)
        collided = bool(
            self.grid is not None and self.grid.segment_collides(motion.start.position, motion.end.position)
        )
        self.pose = motion.end
        return self._obs(), StepInfo(action=action_id, collided=collided, done=action_id == C.ACTION_STOP)

    def close(self) -> None:
        return None

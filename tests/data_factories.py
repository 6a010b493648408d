"""Tiny synthetic episodes and frames for the data tests (poses replayed through sim.dynamics)."""

from __future__ import annotations

import numpy as np

from openfly_agent.data.records import pitch_for_category
from openfly_agent.data.schema import Episode
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.utils.geometry import Pose


def make_episode(
    episode_id: str,
    actions: list[int],
    split: str = "train",
    with_boxes: bool = True,
    seed: int = 0,
    instruction: str | None = None,
) -> Episode:
    """An episode whose poses follow `actions` from a start pose; boxes visible on every other frame."""
    rng = np.random.default_rng(seed)
    start = Pose(float(rng.uniform(-50, 50)), float(rng.uniform(-50, 50)), 30.0, float(rng.uniform(-3, 3)))
    poses = rollout_array(start, actions)[:-1]  # (T, 4): the pose at which each action is taken
    n = len(actions)
    boxes = visible = None
    if with_boxes:
        visible = np.arange(n) % 2 == 0
        boxes = np.zeros((n, 4))
        boxes[visible] = np.column_stack(
            [rng.uniform(0.2, 0.8, (visible.sum(), 2)), rng.uniform(0.05, 0.5, (visible.sum(), 2))]
        )
    return Episode(
        episode_id=episode_id,
        scene_id=episode_id.split("/")[0],
        instruction=instruction or f"fly to the red tower {seed}",
        actions=np.asarray(actions),
        positions=poses[:, :3],
        yaws=poses[:, 3],
        frame_ids=[f"20250101_000000_{t}" for t in range(n)],
        split=split,
        category=episode_id.split("/")[2],
        pitch_deg=pitch_for_category(episode_id.split("/")[2]),
        boxes=boxes,
        box_visible=visible,
        landmark_ids=[f"lm-{seed}"],
    )


def make_frames(n: int, height: int = 12, width: int = 16, seed: int = 0) -> list[np.ndarray]:
    """`n` random (H, W, 3) uint8 RGB frames."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(n)]


def assert_episodes_equal(a: Episode, b: Episode) -> None:
    """Field-by-field equality (arrays exactly)."""
    assert a.episode_id == b.episode_id and a.scene_id == b.scene_id
    assert a.instruction == b.instruction and a.split == b.split and a.category == b.category
    assert a.frame_ids == b.frame_ids and a.landmark_ids == b.landmark_ids and a.pitch_deg == b.pitch_deg
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.yaws, b.yaws)
    np.testing.assert_array_equal(a.goal, b.goal)
    assert (a.leg_goals is None) == (b.leg_goals is None)
    if a.leg_goals is not None:
        np.testing.assert_array_equal(a.leg_goals, b.leg_goals)
    assert (a.boxes is None) == (b.boxes is None)
    if a.boxes is not None:
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.box_visible, b.box_visible)

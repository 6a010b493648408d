"""Raw primitives -> the action codebook (merged 6 / 9 m forwards), replay through the dynamics, categories.

Merged labels sit at the frame where their motion starts (DESIGN decision; the release attaches them to the
block's last frame), so `positions[t + 1], yaws[t + 1] == apply_action(pose[t], actions[t])` for every
t < T - 1. The last navigation label is STOP (0). Optional take-off (-1 climbs before) and landing
(-2 after STOP, as the release orders them): STOP does not move, so the first landing frame repeats the
STOP pose, and the last landing label (the landed frame) is not executed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim import dynamics
from openfly_agent.toolchain.config import CategoryConfig
from openfly_agent.utils.geometry import Pose, path_length

_MERGED_FORWARD = {3: C.ACTION_FORWARD_9, 2: C.ACTION_FORWARD_6, 1: C.ACTION_FORWARD}


@dataclass
class ActionSequence:
    """Kept frames of one trajectory: their labels, raw primitive indices and replayed poses."""

    actions: np.ndarray  # (T,) int64 ids -2..9
    raw_index: np.ndarray  # (T,) int64, index of the frame's first raw primitive (release `index_list` <k>)
    positions: np.ndarray  # (T, 3) metres, replayed through sim/dynamics.py
    yaws: np.ndarray  # (T,) radians, wrapped to (-pi, pi] by the dynamics

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def poses(self) -> list[Pose]:
        return [Pose(*p, y) for p, y in zip(self.positions, self.yaws)]


def merge_forward(primitives: list[int]) -> tuple[list[int], list[int]]:
    """Fold runs of 3 m forward primitives into blocks of 9 m, then one 6 m or 3 m remainder.

    Returns:
        (labels, raw indices): one label per kept frame and the index of its block's first primitive.

    >>> merge_forward([1, 1, 1, 1, 1, 2, 1])
    ([9, 8, 2, 1], [0, 3, 5, 6])
    """
    labels, raw, i = [], [], 0
    while i < len(primitives):
        if primitives[i] != C.ACTION_FORWARD:
            labels.append(int(primitives[i]))
            raw.append(i)
            i += 1
            continue
        run = i
        while run < len(primitives) and primitives[run] == C.ACTION_FORWARD:
            run += 1
        while i < run:
            block = min(3, run - i)
            labels.append(_MERGED_FORWARD[block])
            raw.append(i)
            i += block
    return labels, raw


def build_action_sequence(
    start: Pose, nav_primitives: list[int], takeoff_steps: int = 0, landing_steps: int = 0
) -> ActionSequence:
    """Codebook labels + replayed poses of: take-off climbs, navigation, STOP, landing descents.

    Args:
        start: pose of the first frame (on the ground when `takeoff_steps` > 0).
        nav_primitives: A* primitives (1..5) of the navigation segment, without STOP.
        takeoff_steps: 3 m climbs (-1) before the navigation segment.
        landing_steps: 3 m descents (-2) after STOP; adds landing_steps + 1 frames (see the module docstring).
    """
    for p in nav_primitives:
        if p not in (
            C.ACTION_FORWARD,
            C.ACTION_TURN_LEFT,
            C.ACTION_TURN_RIGHT,
            C.ACTION_ASCEND,
            C.ACTION_DESCEND,
        ):
            raise ValueError(f"navigation primitives must be 1..5 (3 m / 30 deg), got {p}")
    raw = [C.ACTION_TAKEOFF] * takeoff_steps + list(nav_primitives) + [C.ACTION_STOP]
    if landing_steps:
        raw += [C.ACTION_LANDING] * (landing_steps + 1)
    labels, raw_index = merge_forward(raw)
    poses = dynamics.rollout_array(start, labels[:-1])  # (T, 4): the last label is never executed
    return ActionSequence(
        actions=np.asarray(labels, dtype=np.int64),
        raw_index=np.asarray(raw_index, dtype=np.int64),
        positions=poses[:, :3].copy(),
        yaws=poses[:, 3].copy(),
    )


def navigation_mask(actions: np.ndarray) -> np.ndarray:
    """(T,) bool: frames of the navigation segment (not take-off climbs, not frames after STOP)."""
    actions = np.asarray(actions)
    stop = (
        int(np.flatnonzero(actions == C.ACTION_STOP)[0])
        if (actions == C.ACTION_STOP).any()
        else len(actions) - 1
    )
    mask = np.zeros(len(actions), dtype=bool)
    mask[: stop + 1] = True
    mask &= actions != C.ACTION_TAKEOFF
    return mask


def categorize(flight_height_m: float, length_m: float, cfg: CategoryConfig, updown: bool = False) -> str:
    """Release category name, e.g. `medium_average` or `low_long_updown`."""
    h_lo, h_hi = cfg.height_bins_m
    l_lo, l_hi = cfg.length_bins_m
    height = "low" if flight_height_m < h_lo else ("medium" if flight_height_m < h_hi else "high")
    length = "short" if length_m < l_lo else ("average" if length_m < l_hi else "long")
    return f"{height}_{length}" + ("_updown" if updown else "")


def sequence_category(seq: ActionSequence, elevation: float, cfg: CategoryConfig) -> str:
    """Category of a sequence: mean navigation height above the elevation and navigation path length."""
    nav = navigation_mask(seq.actions)
    height = float(np.mean(seq.positions[nav, 2])) - elevation
    updown = bool(np.isin(seq.actions, (C.ACTION_TAKEOFF, C.ACTION_LANDING)).any())
    return categorize(height, path_length(seq.positions[nav]), cfg, updown)


def camera_pitch_for(category: str) -> float:
    """-45 deg for `high_*` categories (DESIGN camera convention), else 0."""
    return C.HIGH_CATEGORY_PITCH_DEG if category.startswith("high") else 0.0

"""Quality filters of the paper: 2..150 actions, damaged frames, flying below tree height.

Each check returns None when the trajectory passes, else a short reason that the summary counts.
"""

from __future__ import annotations

import numpy as np

from openfly_agent.toolchain.actions import navigation_mask
from openfly_agent.toolchain.config import FilterConfig

REASON_TOO_SHORT = "too_few_actions"
REASON_TOO_LONG = "too_many_actions"
REASON_DAMAGED = "damaged_frame"
REASON_LOW = "below_tree_height"


def check_action_count(actions: np.ndarray, cfg: FilterConfig) -> str | None:
    """Number of labelled frames (take-off / landing included) must lie in [min_actions, max_actions]."""
    n = len(actions)
    if n < cfg.min_actions:
        return REASON_TOO_SHORT
    if n > cfg.max_actions:
        return REASON_TOO_LONG
    return None


def is_damaged_frame(rgb: np.ndarray, cfg: FilterConfig) -> bool:
    """A frame that is (nearly) one colour: pixel std below `min_frame_std`, or one colour dominating.

    Catches black / failed renders and a camera inside geometry. The dominant colour is counted on a 4x
    subsampled frame.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.size == 0:
        return True
    if float(rgb.std()) < cfg.min_frame_std:
        return True
    small = rgb[::4, ::4].reshape(-1, 3).astype(np.int32)
    packed = (small[:, 0] << 16) | (small[:, 1] << 8) | small[:, 2]
    _, counts = np.unique(packed, return_counts=True)
    return counts.max() / len(packed) > cfg.max_dominant_fraction


def check_frames(frames: list[np.ndarray], cfg: FilterConfig) -> str | None:
    return REASON_DAMAGED if any(is_damaged_frame(f, cfg) for f in frames) else None


def check_height(
    positions: np.ndarray, actions: np.ndarray, ground_z: float, tree_height_m: float
) -> str | None:
    """Navigation frames (not take-off / landing) must fly at least `tree_height_m` above the ground."""
    nav = navigation_mask(actions)
    if np.any(np.asarray(positions)[nav, 2] < ground_z + tree_height_m):
        return REASON_LOW
    return None

"""Per-step training samples: instruction, current frame, memory keyframe sets, action and landmark box.

No tokenisation here (the collator does it). The keyframe selector comes from the model package and is
injected by the caller, so `data/` never imports `model/`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.config import HISTORY_MODES, DataConfig
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.schema import Episode

logger = logging.getLogger(__name__)


class KeyframeSelector(Protocol):
    """What the dataset needs from model/memory/keyframes.py."""

    def select(self, actions: np.ndarray, box_areas: list[float | None] | None, t: int) -> list[list[int]]:
        """Keyframe sets for step t: lists of frame indices < t, oldest set first.

        `box_areas[j]` is frame j's box area (w * h), None where the landmark is not visible; the whole
        argument is None when boxes are unknown (area test skipped).
        """
        ...


def box_areas(episode: Episode) -> list[float | None] | None:
    """Box area w * h per frame (None where not visible), or None for an episode without boxes."""
    if episode.boxes is None:
        return None
    areas = episode.boxes[:, 2] * episode.boxes[:, 3]  # (T,)
    return [float(a) if v else None for a, v in zip(areas, episode.box_visible)]


class NavigationStepDataset(torch.utils.data.Dataset):
    """One sample per step t whose action is a model action (0..9); -1 / -2 steps only serve as history.

    A sample (`__getitem__`) is a dict of numpy / python values:
    `instruction` str, `rgb` (H, W, 3) uint8 (frame t), `memory` list of up to K sets, each a list of up
    to S `(rgb (H, W, 3) uint8, box (4,) float32, visible bool)` oldest first, `action` int,
    `box` (4,) float32 (zeros when not visible), `box_visible` bool, `episode_id` str, `step_index` int.

    History modes:
        "keyframes": `keyframe_selector.select(actions[:t], box_areas[:t], t)` (only the past is shown, so
            the label at t cannot leak); areas are w * h, None where the landmark is not visible. Without
            boxes (released OpenFly data) `box_areas` is None: the selector skips its area test and the
            sets come from motion change points alone. The last K sets are kept, each cut to its last S
            frames.
        "uniform": K single-frame sets at frames `round(linspace(0, t - 1, min(K, t)))`.
        "random": K distinct random earlier frames (sorted), drawn from a generator seeded with
            (seed, epoch, sample index): reproducible across workers and runs; `set_epoch` varies it.
        "none": no memory.

    Args:
        episodes: the episodes (reader options already applied).
        frames: resolves frame ids to RGB.
        history: one of "keyframes", "uniform", "random", "none" (`data.history.mode`).
        capacity: K, memory sets per sample (the model's `memory.capacity`).
        set_size: S, frames per set (the model's keyframe set size, 2 x radius + 1).
        keyframe_selector: required for history "keyframes" (model/memory/keyframes.py).
        seed: seed of the "random" mode.
    """

    def __init__(
        self,
        episodes: Sequence[Episode],
        frames: FrameStore,
        history: str,
        capacity: int,
        set_size: int,
        keyframe_selector: KeyframeSelector | None = None,
        seed: int = 0,
        target_attributes: Callable[[str, str], np.ndarray] | None = None,
    ):
        if history not in HISTORY_MODES:
            raise ValueError(f"history={history!r}: choose one of {HISTORY_MODES}")
        if capacity < 0 or set_size < 1:
            raise ValueError(
                f"capacity={capacity}, set_size={set_size}: need capacity >= 0 and set_size >= 1"
            )
        if history == "keyframes" and keyframe_selector is None:
            raise ValueError(
                "history='keyframes' needs keyframe_selector (the model's keyframe selector, e.g. "
                "model.keyframes.KeyframeSelector); or choose history='uniform' | 'random' | 'none'"
            )
        self.history, self.capacity, self.set_size = history, capacity, set_size
        self.episodes = list(episodes)
        self.frames = frames
        self.keyframe_selector = keyframe_selector
        # (scene id, landmark id) -> (4,) attribute ids of the target (model.grounding.attribute_weight)
        self.target_attributes = target_attributes
        self.seed, self.epoch = seed, 0
        index = [
            (e, t)
            for e, episode in enumerate(self.episodes)
            for t in np.flatnonzero((episode.actions >= 0) & (episode.actions < C.NUM_ACTIONS))
        ]
        self._index = np.asarray(index, dtype=np.int64).reshape(-1, 2)  # (N, 2) episode index, step
        self._areas = [box_areas(e) for e in self.episodes]
        logger.info("%d training steps from %d episodes (history=%s)", len(self), len(self.episodes), history)

    def __len__(self) -> int:
        return len(self._index)

    def set_epoch(self, epoch: int) -> None:
        """Change the draws of the "random" history mode (call once per epoch)."""
        self.epoch = int(epoch)

    def locate(self, index: int) -> tuple[Episode, int]:
        """(episode, step t) of sample `index`."""
        e, t = self._index[index]
        return self.episodes[int(e)], int(t)

    def memory_indices(self, index: int) -> list[list[int]]:
        """Frame indices of the memory sets of sample `index`, oldest set first (all < t)."""
        episode, t = self.locate(index)
        k, mode = self.capacity, self.history
        if mode == "none" or k == 0 or t == 0:
            return []
        if mode == "uniform":
            picks = np.unique(np.round(np.linspace(0, t - 1, min(k, t))).astype(int))
            return [[int(j)] for j in picks]
        if mode == "random":
            rng = np.random.default_rng([self.seed, self.epoch, index])
            return [[int(j)] for j in np.sort(rng.choice(t, size=min(k, t), replace=False))]
        areas = self._areas[int(self._index[index][0])]
        sets = self.keyframe_selector.select(
            episode.actions[:t].copy(), None if areas is None else areas[:t], t
        )
        return self._clean_sets(sets, episode, t)

    def _clean_sets(self, sets, episode: Episode, t: int) -> list[list[int]]:
        cleaned = []
        for frame_set in sets:
            frame_set = sorted(int(j) for j in frame_set)
            if any(not 0 <= j < t for j in frame_set):
                raise ValueError(
                    f"keyframe selector returned frames {frame_set} for step {t} of {episode.episode_id}; "
                    f"memory frames must be in [0, {t})"
                )
            if frame_set:
                cleaned.append(frame_set[-self.set_size :])
        cleaned.sort(key=lambda s: s[0])
        return cleaned[-self.capacity :]

    def _box(self, episode: Episode, t: int) -> tuple[np.ndarray, bool]:
        if episode.boxes is None or not episode.box_visible[t]:
            return np.zeros(4, dtype=np.float32), False
        return episode.boxes[t].astype(np.float32), True

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} out of range 0..{len(self) - 1}")
        episode, t = self.locate(index)
        memory = [
            [(self.frames.frame(episode, j), *self._box(episode, j)) for j in frame_set]
            for frame_set in self.memory_indices(index)
        ]
        box, visible = self._box(episode, t)
        sample = {
            C.OBS_INSTRUCTION: episode.instruction,
            C.OBS_RGB: self.frames.frame(episode, t),
            C.MEMORY: memory,
            C.ACTION: int(episode.actions[t]),
            C.BOX: box,
            C.BOX_VISIBLE: visible,
            C.EPISODE_ID: episode.episode_id,
            C.STEP_INDEX: t,
        }
        if self.target_attributes is not None:
            target = episode.landmark_ids[-1] if episode.landmark_ids else ""
            sample[C.TARGET_ATTRIBUTES] = self.target_attributes(episode.scene_id, target)
        return sample


def make_step_dataset(
    cfg: DataConfig,
    split: str,
    capacity: int,
    set_size: int,
    keyframe_selector: KeyframeSelector | None = None,
    seed: int = 0,
) -> NavigationStepDataset:
    """The step dataset of `split` under `cfg.root`, with the reader options and history mode of `cfg`.

    Args:
        cfg: dataset root, reader options, history mode, frame caches.
        split: which split (e.g. `constants.SPLIT_TRAIN`).
        capacity: K, memory sets per sample (the model's `memory.capacity`).
        set_size: S, frames per set (the model's keyframe set size).
        keyframe_selector: required when `cfg.history.mode == "keyframes"`.
        seed: seed of the "random" history mode.
    """
    episodes = load_openfly_dataset(cfg.root, split, cfg.reader)
    frames = FrameStore(cfg.root, cache_episodes=cfg.cache_episodes, cache_frames=cfg.cache_frames)
    return NavigationStepDataset(
        episodes, frames, cfg.history.mode, capacity, set_size, keyframe_selector=keyframe_selector, seed=seed
    )

"""How much memory a history mode gives the samples of a dataset: sets and frames per sample.

A history mode's cost and what it can tell the agent both follow from how often its memory is filled. The
keyframe selector, for instance, adds a set only at a change of motion, so on short, mostly straight routes
most samples have none (docs/experiments/2026-11-26-ablations-on-the-adopted-recipe.md, "The ablation table on the adopted recipe").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from openfly_agent.data.dataset import NavigationStepDataset


@dataclass(frozen=True)
class MemoryOccupancy:
    """Memory of the samples of one dataset under one history mode.

    Attributes:
        history: the dataset's history mode.
        samples: number of samples (model steps).
        sets_per_sample: mean number of memory sets per sample.
        frames_per_sample: mean number of memory frames per sample (all sets together).
        without_memory: fraction of samples with no memory set.
        set_count_fractions: fraction of samples holding exactly k sets, k = 0..capacity.
        episodes_with_memory: fraction of episodes with at least one sample that has memory.
        steps_to_end_median: over the samples with memory, the median number of steps between the sample and
            its episode's last step (None when no sample has memory).
        near_end_fraction: fraction of the samples with memory that lie within `near_end` steps of their
            episode's last step (0.0 when no sample has memory).
    """

    history: str
    samples: int
    sets_per_sample: float
    frames_per_sample: float
    without_memory: float
    set_count_fractions: tuple[float, ...]
    episodes_with_memory: float
    steps_to_end_median: float | None
    near_end_fraction: float

    def to_dict(self) -> dict:
        return asdict(self)


def memory_occupancy(dataset: NavigationStepDataset, near_end: int = 5) -> MemoryOccupancy:
    """Count the memory sets and frames of every sample of `dataset` and where in its route each one with memory
    lies (frame indices only: no image is read)."""
    if len(dataset) == 0:
        raise ValueError("memory_occupancy: the dataset has no sample")
    sets = [dataset.memory_indices(i) for i in range(len(dataset))]
    set_counts = np.array([len(s) for s in sets])  # (N,)
    frame_counts = np.array([sum(len(frames) for frames in s) for s in sets])  # (N,)
    histogram = np.bincount(set_counts, minlength=dataset.capacity + 1) / len(sets)  # (capacity + 1,)
    located = [dataset.locate(i) for i in range(len(dataset))]
    last_step: dict[str, int] = {}
    for episode, t in located:
        last_step[episode.episode_id] = max(t, last_step.get(episode.episode_id, t))
    with_memory = set_counts > 0  # (N,)
    to_end = np.array([last_step[e.episode_id] - t for (e, t), m in zip(located, with_memory) if m])  # (M,)
    episodes_with_memory = {e.episode_id for (e, _), m in zip(located, with_memory) if m}
    return MemoryOccupancy(
        history=dataset.history,
        samples=len(sets),
        sets_per_sample=float(set_counts.mean()),
        frames_per_sample=float(frame_counts.mean()),
        without_memory=float(histogram[0]),
        set_count_fractions=tuple(float(f) for f in histogram),
        episodes_with_memory=len(episodes_with_memory) / len(last_step),
        steps_to_end_median=float(np.median(to_end)) if len(to_end) else None,
        near_end_fraction=float((to_end < near_end).mean()) if len(to_end) else 0.0,
    )

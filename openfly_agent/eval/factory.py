"""Builders behind `run(cfg)`: the evaluated episodes, the simulator slots and the policies."""

from __future__ import annotations

import logging

from openfly_agent.data.schema import Episode
from openfly_agent.eval.config import EvalConfig

logger = logging.getLogger(__name__)

DEFAULT_FRAME_SIZE = 224


def load_splits(cfg: EvalConfig) -> dict[str, list[Episode]]:
    """{split: episodes sorted by id} for every split of `cfg` (the first `max_episodes` when set).

    Raises:
        FileNotFoundError: the dataset root or a split's annotation is missing, with the path and a hint.
    """
    from openfly_agent.data.openfly_reader import load_openfly_dataset

    out = {}
    for split in cfg.split:
        try:
            episodes = load_openfly_dataset(cfg.dataset_root, split, cfg.reader)
        except FileNotFoundError as err:
            raise FileNotFoundError(
                f"{err}. Generate a dataset first (python -m openfly_agent.toolchain generate "
                "--config configs/toolchain/embedded-small.yaml) or point --dataset_root at one"
            ) from err
        episodes = sorted(episodes, key=lambda e: e.episode_id)
        if cfg.max_episodes is not None:
            episodes = episodes[: cfg.max_episodes]
        if not episodes:
            raise ValueError(f"{cfg.dataset_root}: split {split!r} has no episodes")
        out[split] = episodes
        logger.info("%s: %d episodes from %s", split, len(episodes), cfg.dataset_root)
    return out


def dataset_frame_size(root: str, episodes: list[Episode]) -> tuple[int, int] | None:
    """(height, width) of the dataset frames (its first frame), or None when the dataset has no frames."""
    from openfly_agent.data.frames import FrameStore

    if not episodes:
        return None
    try:
        frame = FrameStore(root).frame(episodes[0], 0)
    except (FileNotFoundError, KeyError, OSError) as err:
        logger.info("no frames under %s (%s); rendering at %d px", root, err, DEFAULT_FRAME_SIZE)
        return None
    return int(frame.shape[0]), int(frame.shape[1])

"""Worker of test_train_distributed.py's epoch test (run under torchrun): which history draws each process sees.

Iterates two epochs of the training loader exactly as `training.train` does (`make_train_loader`, prepared by
accelerate, `epoch_batches`) and writes, per process, one record per sample: epoch, episode, step and a digest
of its memory frames.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.training.accelerator import make_accelerator
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.loaders import epoch_batches, make_train_loader
from openfly_agent.training.state import TrainerState
from openfly_agent.utils.config import parse_config


def memory_digest(sample: dict) -> str:
    """Digest of a sample's memory frames (which earlier frames it was given)."""
    digest = hashlib.sha256()
    for frame_set in sample[C.MEMORY]:
        for rgb, _, _ in frame_set:
            digest.update(rgb.tobytes())
    return digest.hexdigest()


def describe(samples: list[dict]) -> list[tuple[str, int, str]]:
    return [(s[C.EPISODE_ID], int(s[C.STEP_INDEX]), memory_digest(s)) for s in samples]


def make_dataset(cfg: TrainConfig) -> NavigationStepDataset:
    episodes = load_openfly_dataset(cfg.data.root, C.SPLIT_TRAIN, cfg.data.reader)
    return NavigationStepDataset(
        episodes,
        FrameStore(cfg.data.root),
        cfg.data.history.mode,
        cfg.model.memory.capacity,
        cfg.model.keyframes.set_size,
        seed=cfg.seed,
    )


def main(out: str, args: list[str]) -> None:
    cfg = parse_config(TrainConfig, args)
    accelerator = make_accelerator(cfg)
    dataset = make_dataset(cfg)
    loader, _ = make_train_loader(dataset, describe, cfg)
    loader = accelerator.prepare(loader)
    records = []
    for epoch in (0, 1):
        for batch in epoch_batches(loader, dataset, TrainerState(epoch=epoch), accelerator):
            records += [[epoch, *sample] for sample in batch]
    Path(out, f"rank{accelerator.process_index}.json").write_text(json.dumps(records))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])

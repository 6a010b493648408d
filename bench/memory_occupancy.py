"""How full each history mode keeps the memory of a training run's samples (bench/analysis/memory_occupancy.py).

Reads the run's `train_config.json` (data roots, extra train roots, memory capacity, keyframe settings), builds the
samples of one split under each history mode and prints one JSON line per mode: memory sets and frames per
sample, the fraction of samples with no memory, and the fraction holding 0..K sets. Only frame indices are
computed (no image is read, no model is built):

    python bench/memory_occupancy.py --run outputs/recipe/navigation --split train test_unseen

Run it from the directory the training ran in (the run's config names its datasets by relative path).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from openfly_agent import constants as C  # noqa: E402
from openfly_agent.data.config import HISTORY_MODES  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="a training run folder (holds train_config.json)")
    parser.add_argument("--split", nargs="+", default=None, help="default: the train split")
    parser.add_argument("--history", nargs="+", default=["keyframes", "uniform"], choices=HISTORY_MODES)
    args = parser.parse_args()

    # lazy: torch and the training stack; --help stays fast
    from bench.analysis.memory_occupancy import memory_occupancy  # lazy: torch
    from openfly_agent.data.dataset import NavigationStepDataset  # lazy: torch
    from openfly_agent.model.memory.keyframes import KeyframeSelector  # lazy: the model package
    from openfly_agent.training.builder import load_splits  # lazy: torch and transformers
    from openfly_agent.training.config import (
        TrainConfig,
        without_removed_settings,
    )  # lazy: the training stack
    from openfly_agent.utils.config import config_from_dict  # lazy: after the sys.path insert above

    config_path = Path(args.run) / C.TRAIN_CONFIG_NAME
    if not config_path.is_file():
        raise SystemExit(f"{args.run} is not a training run: no {C.TRAIN_CONFIG_NAME}")
    cfg = config_from_dict(TrainConfig, without_removed_settings(json.loads(config_path.read_text())))
    model = cfg.model
    selector = KeyframeSelector.from_config(model.keyframes, model.memory.capacity)
    splits = load_splits(cfg.data, cfg.model.grounding)
    for split in args.split or [C.SPLIT_TRAIN]:
        if split not in splits.episodes:
            raise SystemExit(f"split {split!r} is not one of the run's splits {sorted(splits.episodes)}")
        for history in args.history:
            dataset = NavigationStepDataset(
                splits.episodes[split],
                splits.frames,
                history,
                capacity=model.memory.capacity,
                set_size=model.keyframes.set_size,
                keyframe_selector=selector,
                seed=cfg.seed,
            )
            print(json.dumps({"run": str(args.run), "split": split, **memory_occupancy(dataset).to_dict()}))


if __name__ == "__main__":
    main()

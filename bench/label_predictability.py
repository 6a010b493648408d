"""How much of a generated dataset's expert actions perfect grounding or perfect localisation would explain.

Fits small MLP probes (bench/analysis/label_predictability.py) from privileged per-step features (the target
landmark's ground-truth box; the goal's distance and bearing) to the expert action on the train split and
prints their held-out accuracy on a test split next to the majority-class rate, one JSON line each:

    python bench/label_predictability.py --dataset_root outputs/datasets/embedded-small --split test_unseen

Read it as a ceiling for imitation learners that see only images and text: an agent that grounded the
target perfectly would still be bounded near the box probe's accuracy.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from openfly_agent.data.config import ReaderOptions  # noqa: E402
from openfly_agent.data.openfly_reader import load_openfly_dataset  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--dataset_root", default="outputs/datasets/embedded-small")
    parser.add_argument("--train_split", default="train")
    parser.add_argument("--split", default="test_unseen")
    parser.add_argument(
        "--takeoff_landing", default="trim", help="as data.reader.takeoff_landing in training"
    )
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    import torch

    from bench.analysis.label_predictability import run_probes  # lazy: torch; --help stays fast

    torch.set_num_threads(args.threads)
    options = ReaderOptions(takeoff_landing=args.takeoff_landing)
    train = load_openfly_dataset(args.dataset_root, args.train_split, options)
    test = load_openfly_dataset(args.dataset_root, args.split, options)
    start = time.perf_counter()
    (majority, rate), probes = run_probes(train, test, epochs=args.epochs)
    common = {"dataset": str(args.dataset_root), "train": args.train_split, "test": args.split}
    print(
        json.dumps({**common, "probe": "majority class", "action": majority, "test_accuracy": round(rate, 4)})
    )
    for probe in probes:
        line = {
            **common,
            "probe": probe.name,
            "features": list(probe.features),
            "test_accuracy": round(probe.test_accuracy, 4),
            "train_accuracy": round(probe.train_accuracy, 4),
        }
        print(json.dumps(line))
    print(json.dumps({**common, "seconds": round(time.perf_counter() - start, 1)}))


if __name__ == "__main__":
    main()

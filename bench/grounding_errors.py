"""Where a training run's target boxes go wrong (bench/analysis/grounding_errors.py), as markdown + JSON.

Runs the run's agent (its last checkpoint unless --checkpoint) over evenly spaced samples of its test split (or
--split, of its dataset or --data_root's) and prints IoU by target size and by the target's offset from the
frame's centre, centre hits, size error, argmax-cell hits and the IoU an exact centre or an exact size would give;
--json writes the figures too:

    python bench/grounding_errors.py --run outputs/recipe/grounding --max_samples 1024 --json errors.json

Run it from the directory the training ran in (the run's config names its datasets by relative path).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def centre_window_arg(value: str) -> int | None | str:
    """--centre_window: "checkpoint" (keep the checkpoint's), "none" (every cell) or an int >= 0."""
    if value == "checkpoint":
        return value
    if value == "none":
        return None
    if not value.isdigit():
        raise argparse.ArgumentTypeError(f"checkpoint, none or an int >= 0, got {value!r}")
    return int(value)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="a training run folder (holds train_config.json)")
    parser.add_argument("--checkpoint", default=None, help="a checkpoint of the run (default: its last)")
    parser.add_argument("--split", default=None, help="default: the run's data.test_split")
    parser.add_argument(
        "--data_root",
        default=None,
        help="read the split from this dataset root (default: the run's data.root)",
    )
    parser.add_argument("--max_samples", type=int, default=1024, help="0: every sample of the split")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    parser.add_argument(
        "--centre_window",
        type=centre_window_arg,
        default="checkpoint",
        help="decode with this grounding.centre_window (an int, or none: every cell); default: the checkpoint's",
    )
    parser.add_argument(
        "--live_weights",
        action="store_true",
        help="score the live weights of the checkpoint's training state (a run with optim.ema_decay exports the average)",
    )
    args = parser.parse_args()

    import torch  # lazy: --help stays fast

    from bench.analysis.grounding_errors import (  # lazy: torch and the model; --help stays fast
        collect_target_boxes,
        errors_markdown,
        grounding_errors,
    )

    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    boxes = collect_target_boxes(
        args.run,
        args.checkpoint,
        args.split,
        args.max_samples or None,
        args.batch_size,
        args.centre_window,
        args.live_weights,
        args.data_root,
    )
    errors = grounding_errors(boxes.pred, boxes.target, boxes.cell_logits)
    errors.update(split=boxes.split, samples=boxes.samples, visibility_accuracy=boxes.visibility_accuracy)
    print(errors_markdown(errors, title=f"{args.run}, {boxes.split}"))
    print(f"visibility accuracy over {boxes.samples} samples: {boxes.visibility_accuracy:.1%}")
    print(f"{time.perf_counter() - start:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(errors, indent=2) + "\n")


if __name__ == "__main__":
    main()

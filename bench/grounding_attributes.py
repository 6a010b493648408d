"""Where a navigation run's grounding head lands when it misses, and which target attributes its features hold
(bench/analysis/grounding_attributes.py), as markdown (+ JSON):

    python bench/grounding_attributes.py --run outputs/recipe/navigation
    python bench/grounding_attributes.py --run outputs/recipe/navigation --checkpoint outputs/recipe/grounding

Run it from the directory the training ran in (the run's config names its datasets by relative path). About a
minute on 2 cores for the defaults (1,024 test samples rendered again, 3,000 train samples for the probes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--run", required=True, help="a navigation-stage training run (holds train_config.json)"
    )
    parser.add_argument(
        "--checkpoint", default=None, help="weights to read (default: the run's last checkpoint)"
    )
    parser.add_argument("--max_samples", type=int, default=1024, help="test samples (evenly spaced)")
    parser.add_argument("--train_samples", type=int, default=3000, help="train samples the probes are fit on")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args()

    import torch  # lazy: --help stays fast

    from bench.analysis.grounding_attributes import (  # lazy: torch, the model and the simulator
        ATTRIBUTE_FIELDS,
        CELL_SCORES,
        LANDINGS,
        AttributeProbe,
        probe_table,
        rank_summary,
    )

    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    probe = AttributeProbe(args.run, args.checkpoint, args.batch_size)
    test = probe.read("test", args.max_samples, render=True)
    train = probe.read("train", args.train_samples, render=False)
    rows = probe_table(train, test)

    landed = sum(test.landings.values())
    print(
        f"## {args.checkpoint or args.run}: where the predicted centre lands ({landed} visible test targets)\n"
    )
    print("| landing | share |\n|---|---:|")
    for name in LANDINGS:
        print(f"| {name} | {test.landings[name] / max(landed, 1):.1%} |")
    misses = test.shared["misses"]
    shared = {
        name: test.shared[name] / max(misses, 1) for name in (*ATTRIBUTE_FIELDS, "named in the instruction")
    }
    print(f"\nmisses on another landmark ({misses}), sharing the target's: ")
    print(", ".join(f"{name} {share:.0%}" for name, share in shared.items()))
    print("\n| reading of the target's cell | attribute | probe train | probe test | majority |")
    print("|---|---|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['reading']} | {row['attribute']} | {row['train']:.2f} | {row['test']:.2f} | {row['majority']:.2f} |"
        )
    ranks = {name: rank_summary(test.cell_ranks[name]) for name in CELL_SCORES if test.cell_ranks[name]}
    print("\n| the target's cell under | best cell | among the best 3 | median rank |\n|---|---:|---:|---:|")
    for name, summary in ranks.items():
        print(f"| {name} | {summary['best']:.1%} | {summary['top 3']:.1%} | {summary['median']:.0f} |")
    print(f"\n{time.perf_counter() - start:.1f} s")
    if args.json:
        figures = {
            "landings": dict(test.landings),
            "misses": misses,
            "shared": shared,
            "probes": rows,
            "target_cell_ranks": ranks,
        }
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()

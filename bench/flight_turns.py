"""How an evaluated agent turns (bench/analysis/flight_turns.py): turns and reversals per 100 actions, how often it
undoes a turn at once, how often its grounding head switches landmarks while it flies straight (the box's IoU with
the previous step's under 0.2) and how often it turns right after such a switch. One JSON line per policy folder:

    python bench/flight_turns.py outputs/main_job/eval/agent [another eval.py policy folder ...] [--split val]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.analysis.flight_turns import TurnCounts  # noqa: E402
from openfly_agent.eval.compare import load_policy_folder  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy_dirs", nargs="+", help="eval.py policy folders (<output_dir>/<policy>)")
    parser.add_argument("--split", default=None, help="only this split's flights (default: every split)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for folder in args.policy_dirs:
        counts = TurnCounts()
        for record in load_policy_folder(folder).records:
            if args.split is None or record.split == args.split:
                counts.add_flight(record.actions, record.boxes)
        print(json.dumps({"policy_dir": folder, "split": args.split, **counts.summary()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

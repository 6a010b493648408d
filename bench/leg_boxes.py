"""Which landmark an evaluated agent's box is on at each step of a chained route (embedded simulator datasets).

Each flight of an eval.py policy folder is rendered again at every decision pose up to its first collision (where
the standard profile ends it); the box the agent predicted at that step (its record's box) is matched with every
landmark's true box in the frame (bench/analysis/leg_boxes.py): on the target of the leg the drone is on (tracked
as for `--true_box=leg`), on an earlier or a later leg's target, on a landmark the route does not name, or on
none. Boxes on another leg's target say the agent does not know where along the route it is; boxes on no
landmark say its grounding misses the landmarks. For datasets with `leg_goals` (chained routes):

    python bench/leg_boxes.py --policy_dir outputs/long-arms/B/eval/agent \
        --dataset_root outputs/datasets/embedded-long --split val
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.analysis.leg_boxes import LegBoxCounts, leg_box_category  # noqa: E402
from bench.analysis.replay import render_at, replayed_flights  # noqa: E402
from bench.analysis.stop_landmarks import Box  # noqa: E402
from openfly_agent import constants as C  # noqa: E402
from openfly_agent.rollout.legs import current_leg  # noqa: E402


def leg_box_steps(policy_dir: str, dataset_root: str, split: str) -> Iterator[tuple[str, Box | None]]:
    """Every decision step of `split` in `policy_dir` up to its flight's first collision: the category of the
    agent's box and the current leg's target box in the frame (None when out of view)."""
    with replayed_flights(policy_dir, dataset_root, split) as (sim, flights):
        for record, episode in flights:
            if episode.leg_goals is None:
                raise SystemExit(
                    f"{policy_dir}: episode {record.episode_id} of {dataset_root} ({split}) has no `leg_goals` "
                    "(a chained dataset generated since the field exists)"
                )
            steps = len(record.actions) if record.collision_step is None else record.collision_step + 1
            route, leg = episode.landmark_ids, 0
            for t, observation in enumerate(render_at(sim, record, episode, record.poses[:steps])):
                leg = current_leg(leg, np.asarray(record.poses[t][:3]), episode.leg_goals, C.SUCCESS_RADIUS_M)
                boxes = observation.boxes or {}
                yield leg_box_category(record.boxes[t], boxes, route, leg), boxes.get(route[leg])


def count_leg_boxes(policy_dir: str, dataset_root: str, split: str) -> LegBoxCounts:
    """Every decision step of `split` in `policy_dir` up to its flight's first collision, classified."""
    counts = LegBoxCounts()
    for category, target_box in leg_box_steps(policy_dir, dataset_root, split):
        counts.add(category, target_box is not None)
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--policy_dir", required=True, help="an eval.py policy folder, e.g. outputs/eval/agent"
    )
    parser.add_argument("--dataset_root", required=True, help="the generated chained dataset it flew")
    parser.add_argument("--split", default="val")
    parser.add_argument("--json", default=None, help="also write the table's counts to this JSON file")
    args = parser.parse_args()
    counts = count_leg_boxes(args.policy_dir, args.dataset_root, args.split)
    print(f"{args.policy_dir}, {args.split}: every decision step up to the first collision\n")
    print(counts.markdown())
    if args.json:
        rows = [{"on": c, "in_view": a, "out_of_view": b} for c, a, b in counts.table()]
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()

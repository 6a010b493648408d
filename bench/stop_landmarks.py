"""Where an evaluated agent stops, and on what landmark (embedded simulator datasets).

Each flight of an eval.py policy folder that ended with a STOP is rendered again at the STOP's pose; the box the
agent predicted there (its record's last box) is matched with every landmark's true box in that frame
(bench/analysis/stop_landmarks.py): on the route's target, on another landmark the route names, on a landmark
it does not name, or on none. STOPs at the goal (within the profile's success radius) and far from it are
counted apart, with how often the target was in view at a far STOP, and for a STOP on another landmark which of
the target's attributes (type, colour, size, shape, feature) that landmark shares. Read it to tell a hasty STOP near the target
from a flight to the wrong landmark:

    python bench/stop_landmarks.py --policy_dir outputs/main_job/eval/agent \
        --dataset_root outputs/datasets/embedded-small --split test_unseen
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict
from operator import attrgetter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.analysis.replay import render_at, replayed_flights  # noqa: E402
from bench.analysis.stop_landmarks import (  # noqa: E402
    StopRow,
    best_landmark,
    shared_attributes,
    shared_in_view,
    shared_markdown,
    stop_target,
    table_markdown,
)
from openfly_agent.eval.report import episode_rows  # noqa: E402
from openfly_agent.rollout.episodes import target_landmark  # noqa: E402


def classify_stops(policy_dir: str, dataset_root: str, split: str, profile: str) -> list[StopRow]:
    """Every STOP of `split` in `policy_dir`, classified at its pose in the dataset's embedded cities."""
    rows = []
    stopped = attrgetter("stopped")
    with replayed_flights(policy_dir, dataset_root, split, stopped, "ended with a STOP") as (sim, flights):
        scores = episode_rows([record for record, _ in flights], profile)
        for (record, episode), scored in zip(flights, scores):
            target = target_landmark(episode)
            boxes = render_at(sim, record, episode, record.poses[-1:])[0].boxes or {}
            predicted = record.boxes[-1] if record.boxes else None
            on = best_landmark(predicted, boxes)
            landmarks = {b.landmark_id: b.landmark for b in sim.city(record.scene_id).buildings}
            shared, chance = None, None
            if on not in (None, target):
                shared = shared_attributes(landmarks[on], landmarks[target])
                others = [landmarks[i] for i in boxes if i != target and i in landmarks]
                chance = shared_in_view(landmarks[target], others)
            rows.append(
                StopRow(
                    episode_id=record.episode_id,
                    success=bool(scored["success"]),
                    distance_m=math.dist(record.poses[-1][:3], record.goal),
                    target_in_view=target in boxes,
                    on=stop_target(predicted, boxes, target, episode.landmark_ids),
                    shared=shared,
                    shared_in_view=chance,
                )
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--policy_dir", required=True, help="an eval.py policy folder, e.g. outputs/eval/agent"
    )
    parser.add_argument("--dataset_root", required=True, help="the generated dataset it flew")
    parser.add_argument("--split", default="test_unseen")
    parser.add_argument("--profile", default="standard", help="the metric profile whose radius is success")
    parser.add_argument("--json", default=None, help="also write every STOP's row to this JSON file")
    args = parser.parse_args()
    rows = classify_stops(args.policy_dir, args.dataset_root, args.split, args.profile)
    print(f"{args.policy_dir}, {args.split}, `{args.profile}`: {len(rows)} flights ended with a STOP\n")
    print(table_markdown(rows))
    print(shared_markdown(rows))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(row) for row in rows], indent=1) + "\n")


if __name__ == "__main__":
    main()

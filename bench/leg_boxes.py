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
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.analysis.leg_boxes import LegBoxCounts, leg_box_category  # noqa: E402
from openfly_agent import constants as C  # noqa: E402
from openfly_agent.eval.compare import load_policy_folder  # noqa: E402
from openfly_agent.eval.config import EvalConfig  # noqa: E402
from openfly_agent.eval.factory import embedded_sim_config, load_full_splits  # noqa: E402
from openfly_agent.rollout.legs import current_leg  # noqa: E402
from openfly_agent.sim.base import Pose  # noqa: E402
from openfly_agent.sim.embedded import EmbeddedSimulator  # noqa: E402


def count_leg_boxes(policy_dir: str, dataset_root: str, split: str) -> LegBoxCounts:
    """Every decision step of `split` in `policy_dir` up to its flight's first collision, classified."""
    cfg = EvalConfig(checkpoint="unused", dataset_root=dataset_root, split=[split])
    episodes = {e.episode_id: e for e in load_full_splits(cfg)[split]}
    records = [r for r in load_policy_folder(policy_dir).records if r.split == split]
    if not records:
        raise SystemExit(f"{policy_dir}: no flight of split {split}")
    counts = LegBoxCounts()
    with EmbeddedSimulator(embedded_sim_config(cfg, list(episodes.values()))) as sim:
        for record in records:
            episode = episodes.get(record.episode_id)
            if episode is None or episode.leg_goals is None:
                raise SystemExit(
                    f"{policy_dir}: episode {record.episode_id} is not in {dataset_root} ({split}) with "
                    "`leg_goals` (a chained dataset generated since the field exists)"
                )
            steps = len(record.actions) if record.collision_step is None else record.collision_step + 1
            poses = [Pose(*pose) for pose in record.poses[:steps]]
            route, leg = episode.landmark_ids, 0
            # at the camera pitch the flight was flown with (eval renders each episode at its own)
            for t, observation in enumerate(sim.render_many(record.scene_id, poses, episode.pitch_deg)):
                leg = current_leg(leg, np.asarray(record.poses[t][:3]), episode.leg_goals, C.SUCCESS_RADIUS_M)
                boxes = observation.boxes or {}
                category = leg_box_category(record.boxes[t], boxes, route, leg)
                counts.add(category, route[leg] in boxes)
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

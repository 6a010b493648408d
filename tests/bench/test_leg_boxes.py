"""bench/leg_boxes.py: which landmark the agent's box is on at each step of a chained route, by hand and through the
command on the oracle's flights of a generated chained dataset, each step given the box the dataset stores there."""

from __future__ import annotations

import json
import sys

import pytest
from eval_helpers import generate_tiny_dataset

from bench.analysis.leg_boxes import (
    NO_BOX,
    ON_EARLIER,
    ON_LATER,
    ON_LEG,
    ON_NOTHING,
    ON_OTHER,
    LegBoxCounts,
    leg_box_category,
)
from openfly_agent import constants as C
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.eval.config import EvalConfig
from openfly_agent.eval.distributed import read_all_logs
from openfly_agent.eval.run import run
from openfly_agent.utils.config import REPO_ROOT
from openfly_agent.utils.processes import run_group

BOXES = {
    "a": (0.2, 0.5, 0.2, 0.2),
    "b": (0.5, 0.5, 0.2, 0.2),
    "c": (0.8, 0.5, 0.2, 0.2),
    "x": (0.5, 0.2, 0.1, 0.1),
}


@pytest.mark.parametrize(
    ("predicted", "leg", "expected"),
    [
        ((0.5, 0.5, 0.2, 0.2), 1, ON_LEG),  # exactly b's box, on leg 1 (b)
        ((0.52, 0.5, 0.2, 0.2), 2, ON_EARLIER),  # b's box shifted 0.02: IoU 0.82, b is leg 1 < 2
        ((0.8, 0.5, 0.2, 0.2), 0, ON_LATER),  # c is leg 2 > 0
        ((0.5, 0.2, 0.1, 0.1), 1, ON_OTHER),  # x is not on the route
        ((0.5, 0.9, 0.1, 0.1), 1, ON_NOTHING),  # overlaps no landmark
        (None, 1, NO_BOX),
    ],
)
def test_categories_by_hand(predicted, leg, expected):
    assert leg_box_category(predicted, BOXES, ["a", "b", "c"], leg) == expected


def test_counts_keep_in_view_apart_and_refuse_an_unknown_category():
    counts = LegBoxCounts()
    for category, in_view in [(ON_LEG, True), (ON_LEG, True), (ON_OTHER, True), (NO_BOX, False)]:
        counts.add(category, in_view)
    assert counts.table()[0] == (ON_LEG, 2, 0) and (NO_BOX, 0, 1) in counts.table()
    assert "| the current leg's target | 2 (66.7 %) | 0 (0.0 %) |" in counts.markdown()
    assert "| all | 3 | 1 |" in counts.markdown()
    with pytest.raises(ValueError, match="unknown category"):
        counts.add("somewhere", True)


def test_the_command_finds_the_datasets_own_boxes_on_route_targets(tmp_path):
    """The oracle replays each chained route; each of its steps is given the box the dataset stores at that frame
    (the toolchain's box of the frame's leg target). Rendered again at the same poses, every such box lies on one
    of the route's targets (the current leg's, or a neighbour's where the toolchain's leg boundary and the 20 m
    tracking differ), and every step without one counts as no box."""
    split = C.SPLIT_TEST_UNSEEN
    dataset = tmp_path / "dataset"
    generate_tiny_dataset(dataset, chained=True)
    run(
        EvalConfig(
            dataset_root=str(dataset), output_dir=str(tmp_path / "eval"), policy="oracle", split=[split]
        )
    )
    folder = tmp_path / "eval" / "oracle"
    episodes = {e.episode_id: e for e in load_openfly_dataset(dataset, split)}
    records = read_all_logs(folder)
    steps = visible = 0
    for record in records:
        episode = episodes[record.episode_id]
        assert len(record.actions) == len(episode.actions) and record.collision_step is None
        record.boxes = [
            [float(v) for v in box] if seen else None for box, seen in zip(episode.boxes, episode.box_visible)
        ]
        steps += len(record.actions)
        visible += sum(box is not None for box in record.boxes)
    (folder / "episodes.jsonl").write_text("".join(r.to_json() + "\n" for r in records))
    out = tmp_path / "legs.json"
    command = [
        sys.executable, str(REPO_ROOT / "bench" / "leg_boxes.py"), f"--policy_dir={folder}",
        f"--dataset_root={dataset}", f"--split={split}", f"--json={out}",
    ]  # fmt: skip
    done = run_group(command, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = {row["on"]: row["in_view"] + row["out_of_view"] for row in json.loads(out.read_text())}
    assert sum(rows.values()) == steps and rows[NO_BOX] == steps - visible
    assert rows[ON_LEG] + rows[ON_EARLIER] + rows[ON_LATER] == visible
    assert rows[ON_LEG] > rows[ON_EARLIER] + rows[ON_LATER]
    assert "| all |" in done.stdout

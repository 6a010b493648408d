"""Which landmark an agent stops on: hand-checked overlaps and categories, then the command on oracle flights of a
generated dataset, whose last box is the target's own."""

from __future__ import annotations

import dataclasses
import json
import sys

import pytest
from eval_helpers import oracle_flights

from bench.analysis.stop_landmarks import (
    NO_BOX,
    ON_NOTHING,
    ON_OTHER_LANDMARK,
    ON_ROUTE_LANDMARK,
    ON_TARGET,
    StopRow,
    box_iou,
    shared_attributes,
    shared_in_view,
    shared_markdown,
    stop_table,
    stop_target,
    table_markdown,
)
from openfly_agent import constants as C
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.eval.distributed import read_all_logs
from openfly_agent.utils.config import REPO_ROOT
from openfly_agent.utils.processes import run_group


def test_box_iou_by_hand():
    a = (0.5, 0.5, 0.2, 0.2)
    assert box_iou(a, a) == pytest.approx(1.0)
    # shifted by half a width: overlap 0.1 x 0.2 = 0.02, union 0.04 + 0.04 - 0.02 = 0.06
    assert box_iou(a, (0.6, 0.5, 0.2, 0.2)) == pytest.approx(1 / 3)
    assert box_iou(a, (0.9, 0.9, 0.1, 0.1)) == 0.0
    assert box_iou((0.5, 0.5, 0.0, 0.0), (0.5, 0.5, 0.0, 0.0)) == 0.0  # empty boxes


def test_stop_target_names_the_best_overlapping_landmark():
    boxes = {"t": (0.3, 0.5, 0.2, 0.4), "r": (0.7, 0.5, 0.2, 0.4), "x": (0.5, 0.2, 0.2, 0.2)}
    route = ["r", "t"]
    assert stop_target((0.3, 0.5, 0.2, 0.4), boxes, "t", route) == ON_TARGET
    assert stop_target((0.72, 0.5, 0.2, 0.4), boxes, "t", route) == ON_ROUTE_LANDMARK
    assert stop_target((0.5, 0.2, 0.2, 0.2), boxes, "t", route) == ON_OTHER_LANDMARK
    # IoU 1/3 with x alone (shifted by half a width): on it; IoU 1/7 (shifted by 3/4): on nothing
    assert stop_target((0.6, 0.2, 0.2, 0.2), boxes, "t", route) == ON_OTHER_LANDMARK
    assert stop_target((0.65, 0.2, 0.2, 0.2), boxes, "t", route) == ON_NOTHING
    assert stop_target((0.5, 0.5, 0.2, 0.2), {}, "t", route) == ON_NOTHING  # no landmark in view
    assert stop_target(None, boxes, "t", route) == NO_BOX


def test_the_table_counts_stops_at_and_far_from_the_goal():
    rows = [
        StopRow("a", True, 5.0, True, ON_TARGET),
        StopRow("b", False, 60.0, False, ON_OTHER_LANDMARK),
        StopRow("c", False, 70.0, True, ON_OTHER_LANDMARK),
        StopRow("d", False, 40.0, True, ON_TARGET),
    ]
    table = {category: counts for category, *counts in stop_table(rows)}
    assert table[ON_TARGET] == [1, 1, 1] and table[ON_OTHER_LANDMARK] == [0, 2, 1]
    assert table[ON_NOTHING] == [0, 0, 0]
    text = table_markdown(rows)
    assert f"| {ON_OTHER_LANDMARK} | 0 | 2 | 1 |" in text and "| all | 1 | 3 | 2 |" in text


def test_shared_attributes_against_the_chance_of_the_landmarks_in_view():
    from openfly_agent.sim.scene import Landmark

    def landmark(name, type_, color, size, shape="rectangular", feature="none"):
        return Landmark(name, type_, color, size, shape, feature, (0.0, 0.0, 0.0))

    target = landmark("t", "tower", "red", "high-rise")
    picked = landmark("p", "tower", "blue", "high-rise")
    others = [picked, landmark("q", "house", "red", "low-rise"), landmark("r", "tower", "red", "low-rise")]
    assert shared_attributes(picked, target) == ["type", "size", "shape", "feature"]
    chance = shared_in_view(target, others)
    assert chance == {"type": 2 / 3, "color": 2 / 3, "size": 1 / 3, "shape": 1.0, "feature": 1.0}
    assert shared_in_view(target, []) == dict.fromkeys(chance, 0.0)
    rows = [
        StopRow("a", False, 60.0, True, ON_OTHER_LANDMARK, shared=["type", "size"], shared_in_view=chance),
        StopRow("b", False, 60.0, True, ON_OTHER_LANDMARK, shared=[], shared_in_view=chance),
        StopRow("c", True, 5.0, True, ON_TARGET),  # at the goal: not counted
    ]
    text = shared_markdown(rows)
    assert "(2): share of them" in text
    assert "| the landmark stopped at | 50 % | 0 % | 50 % | 0 % | 0 % |" in text
    assert "| a landmark in view at random (chance) | 67 % | 67 % | 33 % | 100 % | 100 % |" in text
    assert shared_markdown(rows[2:]) == ""


def test_the_command_finds_oracle_flights_on_their_target(tmp_path):
    """On chained routes (the last frame's box is the final target's), some flown with the camera pitched down:
    each STOP is rendered again at the pitch its flight was flown with."""
    split = C.SPLIT_TEST_UNSEEN
    dataset, folder = oracle_flights(tmp_path, split, chained=True)
    assert {e.pitch_deg for e in load_openfly_dataset(dataset, split)} == {0.0, -45.0}
    # the oracle replays each route to its end; give each flight the target's true box of the route's last frame
    # as the box it "predicted" there (none where the target is out of view)
    episodes = {e.episode_id: e for e in load_openfly_dataset(dataset, split)}
    records = read_all_logs(folder)
    last_boxes = {}
    for record in records:
        episode = episodes[record.episode_id]
        last = [float(v) for v in episode.boxes[-1]] if episode.box_visible[-1] else None
        last_boxes[record.episode_id] = last
        record.boxes = [None] * (len(record.actions) - 1) + [last]
    (folder / "episodes.jsonl").write_text("".join(r.to_json() + "\n" for r in records))
    out = tmp_path / "stops.json"
    command = [
        sys.executable, str(REPO_ROOT / "bench" / "stop_landmarks.py"), f"--policy_dir={folder}",
        f"--dataset_root={dataset}", f"--split={split}", f"--json={out}",
    ]  # fmt: skip
    done = run_group(command, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [StopRow(**row) for row in json.loads(out.read_text())]
    assert len(rows) == len(records) > 0
    for row in rows:
        assert row.success and row.distance_m < 5.0, dataclasses.asdict(row)
        seen = last_boxes[row.episode_id] is not None
        assert row.target_in_view == seen and row.on == (ON_TARGET if seen else NO_BOX), dataclasses.asdict(
            row
        )
    assert sum(row.on == ON_TARGET for row in rows) > 0
    assert f"| all | {len(rows)} | 0 |" in done.stdout

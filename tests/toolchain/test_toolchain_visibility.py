"""Whether the landmark the instruction is talking about is in view (toolchain/visibility.py), and its summary."""

from __future__ import annotations

import numpy as np
import pytest

from openfly_agent.toolchain.instructions import InstructionRequest
from openfly_agent.toolchain.summary import summarize_records, visibility_summary
from openfly_agent.toolchain.visibility import route_visibility


def _box(side: float) -> np.ndarray:
    return np.array([0.5, 0.5, side, side])


def _request(actions, boxes, targets, leg_ends, **kw) -> InstructionRequest:
    return InstructionRequest(np.array(actions), boxes, {}, list(targets), list(leg_ends), **kw)


def test_counts_of_a_hand_checked_route():
    # segments (merge_short_m 9): forward [0, 2) 6 m, left [2, 4), forward [4, 5) 3 m, up [5, 6), then STOP at 6;
    # leg "a" ends at frame 2 (forward [0, 2) names it), leg "b" at the STOP frame 6 (its segment is the climb)
    actions = [9, 9, 2, 2, 9, 4, 0]
    boxes = [
        {"a": _box(0.1)},
        {},
        {"a": _box(0.3), "c": _box(0.2)},
        {"c": _box(0.01)},  # in view, but below min_box_area (0.002 of the frame)
        {"c": _box(0.2)},  # the left turn ends here: it names c
        {"c": _box(0.2), "b": _box(0.04)},  # the 3-m forward run ends here: c (b is below 0.002)
        {"b": _box(0.1)},
    ]
    counts = route_visibility(_request(actions, boxes, ("a", "b"), (2, 6)))
    # clause per frame: a a c c c (climb: names none) b; leg target per frame: a a b b b b b
    assert counts == {
        "decision_steps": 7,
        "clause_steps": 6,
        "clause_hidden": 1,  # frame 1 (a)
        "clause_unseen": 2,  # frames 1 (a) and 3 (c, too small)
        "leg_hidden": 4,  # frames 1 (a), 2, 3, 4 (b)
        "leg_unseen": 5,  # ... and 5 (b, too small)
        "targets_named": 1,  # a by its forward run, b by the closing stop clause
    }


def test_takeoff_and_landing_are_not_decision_steps_and_a_lost_target_counts():
    # take-off, forward 9 m, STOP, landing; legs "a" (ends at frame 2) and "b" (STOP at frame 2) share one clause
    actions = [-1, 9, 0, -2, -2]
    boxes = [{}, {}, {"b": _box(0.1)}, {}, {}]
    counts = route_visibility(_request(actions, boxes, ("a", "b"), (2, 2)))
    assert counts["decision_steps"] == 2 and counts["clause_steps"] == 2  # frames 1 and 2
    assert counts["clause_hidden"] == 1 and counts["leg_hidden"] == 1  # frame 1: b is not in view
    assert counts["targets_named"] == 0  # b took a's clause
    named = route_visibility(_request(actions, boxes, ("a", "b"), (2, 2), name_every_target=True))
    assert named["targets_named"] == 1 and named["clause_hidden"] == 1  # frame 1 now names a, also hidden


def test_summary_pools_the_counts_and_reports_the_p90():
    records = [
        {"status": "ok", "split": "train", "scene_id": "s", "category": "c", "actions": [1, 0],
         "path_length_m": float(length), "landmarks": 3, "decision_steps": 10, "clause_steps": 8,
         "clause_hidden": 2, "clause_unseen": 4, "leg_hidden": 5, "leg_unseen": 6, "targets_named": 1}
        for length in range(10, 110, 10)
    ]  # fmt: skip
    records[0].update(landmarks=4, clause_steps=2, clause_hidden=2, targets_named=0)
    records.append({"status": "ok", "split": "train", "scene_id": "s", "category": "c", "kind": "dagger"})
    summary = summarize_records(records)
    assert summary["landmarks_per_route"] == {"3": 9, "4": 1}
    assert summary["path_length_m"]["median"] == 55.0 and summary["path_length_m"]["p90"] == pytest.approx(
        91.0
    )
    vis = visibility_summary(records)
    assert vis["routes"] == 10 and vis["decision_steps"] == 100 and vis["clause_steps"] == 9 * 8 + 2
    assert vis["clause_hidden_share"] == pytest.approx(20 / 74)  # 9 x 2 + 2 hidden of 74
    assert vis["clause_unseen_share"] == pytest.approx(40 / 74)
    assert vis["leg_hidden_share"] == 0.5 and vis["leg_unseen_share"] == 0.6
    assert vis["targets_named_share"] == 0.9
    assert summary["visibility"] == vis


def test_an_after_passing_clause_counts_the_target_just_passed():
    # forward [0, 2) to "a" (leg 1 ends at frame 2), left turn [2, 5), forward [5, 7) to "b", STOP at 7; during
    # the turn "a" leaves the frame (frames 3, 4) and "b" comes in (frame 3 on)
    actions = [9, 9, 2, 2, 2, 9, 9, 0]
    boxes = [{"a": _box(0.3)}] * 3 + [{"b": _box(0.3)}] * 5
    plain = route_visibility(_request(actions, boxes, ("a", "b"), (2, 7)))
    # the turn names b (seen where it ends): b is hidden at frame 2 only
    assert plain["clause_steps"] == 8 and plain["clause_hidden"] == 1 and plain["leg_hidden"] == 1
    passed = route_visibility(_request(actions, boxes, ("a", "b"), (2, 7), name_passed_landmark=True))
    # "after passing a, turn left to face b": a decides when to turn, and is hidden at frames 3 and 4
    assert passed == {
        "decision_steps": 8,
        "clause_steps": 8,
        "clause_hidden": 2,
        "clause_unseen": 2,
        "leg_hidden": 1,  # frame 2: the leg target is already b
        "leg_unseen": 1,
        "targets_named": 1,
    }

"""Label options: take-off / landing phases and where merged 6 / 9 m forward labels sit."""

from __future__ import annotations

import numpy as np
import pytest

from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.labels import (
    apply_reader_options,
    apply_takeoff_landing,
    check_action_sequence,
    move_merged_forward_to_start,
)
from openfly_agent.data.openfly_reader import ReadReport, read_annotation_file
from openfly_agent.data.schema import Episode, SchemaError
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.utils.geometry import Pose

F, L, U, STOP = 1, 2, 4, 0  # forward 3 m, turn left, ascend, stop


def released_merge(raw_actions: list[int], start: Pose) -> Episode:
    """Build an episode as the release does: raw 3 m primitives, forward runs merged into blocks of 3 / 2 / 1
    labelled 9 / 8 / 1 on the block's LAST raw frame, intermediate raw frames dropped."""
    poses = rollout_array(start, raw_actions)  # raw frame k = pose before primitive k
    kept, labels, k = [], [], 0
    while k < len(raw_actions):
        if raw_actions[k] != F:
            kept.append(k)
            labels.append(raw_actions[k])
            k += 1
            continue
        run = next((j for j in range(k, len(raw_actions)) if raw_actions[j] != F), len(raw_actions)) - k
        for size in [3] * (run // 3) + ([run % 3] if run % 3 else []):
            kept.append(k + size - 1)
            labels.append({3: 9, 2: 8, 1: 1}[size])
            k += size
    return Episode(
        episode_id="env_x/astar_data/low_short/hand",
        scene_id="env_x",
        instruction="hand-made",
        actions=np.asarray(labels),
        positions=poses[kept, :3],
        yaws=poses[kept, 3],
        frame_ids=[f"20250101_000000_{k}" for k in kept],
    )


def test_merged_forward_start_on_hand_made_episode():
    # raw: 7 forwards, turn left, 3 forwards, climb, 3 forwards, stop
    raw = [F] * 7 + [L] + [F] * 3 + [U] + [F] * 3 + [STOP]
    episode = released_merge(raw, Pose(10.0, -5.0, 30.0, 0.0))
    # kept raw frames 2, 5, 6 (blocks 3, 3, 1), 7 (turn), 10 (block 3), 11 (climb), 14 (block 3), 15 (stop)
    assert [int(f.rsplit("_", 1)[1]) for f in episode.frame_ids] == [2, 5, 6, 7, 10, 11, 14, 15]
    assert episode.actions.tolist() == [9, 9, 1, 2, 9, 4, 9, 0]
    moved, changed, unresolved = move_merged_forward_to_start(episode)
    # Displacements to the next kept frame: 9 m, 3 m, 3 m, (turn + 6 m), 3 m, (climb + 6 m), 3 m.
    assert moved.actions.tolist() == [9, 1, 1, 2, 1, 4, 1, 0]
    assert (changed, unresolved) == (3, 0)
    np.testing.assert_array_equal(moved.positions, episode.positions)  # only labels move


def test_merged_forward_start_leaves_non_pure_moves_unresolved():
    episode = released_merge([F, F, F, F, F, F, STOP], Pose(0.0, 0.0, 10.0, 1.0))
    assert episode.actions.tolist() == [9, 9, 0]
    assert move_merged_forward_to_start(episode)[0].actions.tolist() == [9, 1, 0]  # 3 m from frame 1 to STOP
    episode.positions[2, :2] += 2.0 * np.array([-np.sin(1.0), np.cos(1.0)])  # STOP frame 2 m to the left
    moved, changed, unresolved = move_merged_forward_to_start(episode)
    assert moved.actions.tolist() == [9, 9, 0] and (changed, unresolved) == (0, 1)


def test_merged_forward_start_on_eval_test_record_0(openfly_fixtures):
    episode = read_annotation_file(openfly_fixtures / "eval_test.json", ReaderOptions())[0]
    assert episode.actions.tolist() == [9, 9, 9, 9, 9, 9, 9, 3, 9, 1, 2, 9, 9, 9, 9, 0]
    report = ReadReport()
    start = read_annotation_file(
        openfly_fixtures / "eval_test.json", ReaderOptions(merged_forward_position="start"), report=report
    )[0]
    assert (report.forward_relabelled, report.forward_unresolved) == (724, 21)  # of 2405 forward frames
    # frame _20 is 3 m before the turn frame _21; _24 is 3 m before _25; _38 is 3 m before the STOP frame _39
    assert start.actions.tolist() == [9, 9, 9, 9, 9, 9, 1, 3, 1, 1, 2, 9, 9, 9, 1, 0]


def _updown() -> Episode:
    actions = [-1, -1, 9, 2, 0, -2, -2]
    poses = rollout_array(Pose(0.0, 0.0, 0.0, 0.0), [-1, -1, 9, 2, 5, 5])  # STOP frame, then 3 m descents
    return Episode(
        episode_id="env_x/astar_data/low_short_updown/ud",
        scene_id="env_x",
        instruction="x",
        actions=np.asarray(actions),
        positions=poses[:, :3],
        yaws=poses[:, 3],
        frame_ids=[str(t) for t in range(7)],
        boxes=np.tile([0.5, 0.5, 0.2, 0.2], (7, 1)),
        box_visible=np.ones(7, bool),
    )


def test_takeoff_landing_options():
    episode = _updown()
    keep = apply_takeoff_landing(episode, "keep")
    assert keep.actions.tolist() == [-1, -1, 9, 2, 0, -2, -2]
    mapped = apply_takeoff_landing(episode, "map")
    assert mapped.actions.tolist() == [4, 4, 9, 2, 5, 5, 0]
    np.testing.assert_array_equal(mapped.goal, episode.positions[-1])  # the landed point, as released
    trimmed = apply_takeoff_landing(episode, "trim")
    assert trimmed.actions.tolist() == [9, 2, 0] and trimmed.frame_ids == ["2", "3", "4"]
    assert trimmed.boxes.shape == (3, 4) and trimmed.box_visible.shape == (3,)
    np.testing.assert_array_equal(trimmed.goal, episode.positions[4])  # the STOP pose
    assert episode.actions.tolist() == [-1, -1, 9, 2, 0, -2, -2]  # the input is not modified


@pytest.mark.parametrize(
    ("actions", "problem"),
    [
        ([9, 1], "exactly one STOP"),
        ([9, 0, 1], "only landing"),
        ([9, -2, 0], "landing (-2) before"),
        ([-1, 9, -1, 0], "take-off (-1) after"),
        ([9, 12, 0], "unknown action"),
    ],
)
def test_check_action_sequence(actions, problem):
    with pytest.raises(SchemaError, match=problem.replace("(", r"\(").replace(")", r"\)")) as info:
        check_action_sequence(np.asarray(actions), "f.json", 7)
    assert (info.value.file, info.value.record, info.value.field_name) == ("f.json", 7, "action")


def test_apply_reader_options_checks_first():
    episode = _updown()
    episode.actions[3] = 0
    with pytest.raises(SchemaError, match="one STOP"):
        apply_reader_options(episode, ReaderOptions(), "f.json", 0)

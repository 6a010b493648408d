"""Episode records and their JSONL log: round trips, partial last lines, corrupt lines, rank-log merging."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent.eval.distributed import ProcessInfo, log_files, log_name, merge_logs, read_all_logs, shard
from openfly_agent.eval.records import EpisodeLog, RecordError, read_jsonl
from openfly_agent.rollout.record import EpisodeRecord


def _record(episode_id="s/astar_data/low_short/t0", split="test_seen", actions=(1, 1, 0), collisions=()):
    poses = [[0.0, 0.0, 10.0, 0.0]]
    for a in actions:
        x = poses[-1][0] + (3.0 if a == 1 else 0.0)
        poses.append([x, 0.0, 10.0, 0.0])
    return EpisodeRecord(
        split=split,
        episode_id=episode_id,
        scene_id="s",
        policy="stop",
        instruction="go",
        goal=[6.0, 0.0, 10.0],
        reference_path=[[0.0, 0.0, 10.0], [6.0, 0.0, 10.0]],
        actions=list(actions),
        poses=poses,
        stopped=bool(actions) and actions[-1] == 0,
        end_reason="stop" if actions and actions[-1] == 0 else "max_steps",
        collision_steps=list(collisions),
        boxes=[None] * len(actions),
        keyframes=[None] * len(actions),
    )


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 9), max_size=12), st.booleans())
def test_record_json_round_trip(moves, stop):
    record = _record(actions=tuple(moves) + ((0,) if stop else ()))
    back = EpisodeRecord.from_dict(json.loads(record.to_json()))
    assert back == record
    assert back.stop_step == (len(moves) if stop else None)


def test_log_appends_and_reads_back(tmp_path):
    log = EpisodeLog(tmp_path / "episodes.jsonl")
    records = [_record(f"s/a/b/t{i}") for i in range(3)]
    for r in records:
        log.append(r)
    assert read_jsonl(tmp_path / "episodes.jsonl") == records
    assert EpisodeLog(tmp_path / "episodes.jsonl").existing == records


def test_partial_last_line_is_dropped_with_a_warning_and_truncated(tmp_path, caplog):
    path = tmp_path / "episodes.jsonl"
    full = [_record(f"s/a/b/t{i}") for i in range(2)]
    text = "".join(r.to_json() + "\n" for r in full) + _record("s/a/b/t9").to_json()[:57]
    path.write_text(text)
    with caplog.at_level("WARNING"):
        assert read_jsonl(path) == full
    assert "line 3" in caplog.text and str(path) in caplog.text
    assert path.read_text() == text  # reading alone does not change the file
    log = EpisodeLog(path)  # opening the log for appending cuts the partial line
    assert log.existing == full
    log.append(_record("s/a/b/t5"))
    assert [r.episode_id for r in read_jsonl(path)] == ["s/a/b/t0", "s/a/b/t1", "s/a/b/t5"]


def test_complete_last_record_without_newline_is_kept(tmp_path):
    path = tmp_path / "episodes.jsonl"
    path.write_text(_record("s/a/b/t0").to_json())
    log = EpisodeLog(path)
    log.append(_record("s/a/b/t1"))
    assert [r.episode_id for r in read_jsonl(path)] == ["s/a/b/t0", "s/a/b/t1"]


def test_corrupt_middle_line_names_file_line_and_field(tmp_path):
    path = tmp_path / "episodes.jsonl"
    path.write_text(_record().to_json() + "\n{not json\n" + _record("x").to_json() + "\n")
    with pytest.raises(RecordError, match=r"episodes.jsonl:2: field '<line>'"):
        read_jsonl(path)
    bad = json.loads(_record().to_json())
    bad["poses"] = bad["poses"][:-1]
    path.write_text(json.dumps(bad) + "\n")
    with pytest.raises(RecordError, match=r"jsonl:1: field 'poses': 3 poses for 3 actions"):
        read_jsonl(path)
    del bad["stopped"]
    path.write_text(json.dumps(bad) + "\n")
    with pytest.raises(RecordError, match="field 'stopped': missing"):
        read_jsonl(path)


def test_shards_cover_every_item_once():
    items = list(range(11))
    parts = [shard(items, r, 3) for r in range(3)]
    assert sorted(sum(parts, [])) == items
    assert parts[1] == [1, 4, 7, 10]
    with pytest.raises(ValueError, match="rank 3"):
        shard(items, 3, 3)


def test_rank_logs_merge_into_one_file(tmp_path):
    assert log_name(ProcessInfo(0, 1)) == "episodes.jsonl"
    assert log_name(ProcessInfo(1, 2)) == "episodes.rank1.jsonl"
    a, b, c = (_record(f"s/a/b/t{i}") for i in range(3))
    EpisodeLog(tmp_path / "episodes.rank0.jsonl").append(a)
    EpisodeLog(tmp_path / "episodes.rank1.jsonl").append(c)
    EpisodeLog(tmp_path / "episodes.rank1.jsonl").append(b)
    assert [p.name for p in log_files(tmp_path)] == ["episodes.rank0.jsonl", "episodes.rank1.jsonl"]
    merged = merge_logs(tmp_path)
    assert merged == [a, b, c]
    assert [p.name for p in log_files(tmp_path)] == ["episodes.jsonl"]
    assert read_all_logs(tmp_path) == [a, b, c]

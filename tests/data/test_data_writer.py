"""Writer -> reader round trips, `datasets` streaming over written files, resume and shard merge."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from data_factories import assert_episodes_equal, make_episode, make_frames

from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset, read_annotation_file
from openfly_agent.data.parquet_io import read_parquet_episode
from openfly_agent.data.schema import SchemaError
from openfly_agent.data.stats import compute_action_statistics
from openfly_agent.data.writer import OpenFlyDatasetWriter

KEEP = ReaderOptions(takeoff_landing="keep")


def _episodes():
    return [
        make_episode("embedded-1/astar_data/high_short/traj_a", [9, 2, 9, 1, 0], "train", seed=1),
        make_episode("embedded-1/astar_data/low_short/traj_b", [-1, 8, 3, 9, 0, -2], "train", seed=2),
        make_episode("embedded-2/astar_data/low_average/traj_c", [1, 1, 4, 0], "test_seen", seed=3),
        make_episode(
            "embedded-9/astar_data/low_short/traj_d", [9, 0], "test_unseen", with_boxes=False, seed=4
        ),
    ]


def _write_all(root, episodes, image_format="png"):
    writer = OpenFlyDatasetWriter(root, image_format=image_format)
    frames = {}
    for i, episode in enumerate(episodes):
        frames[episode.episode_id] = make_frames(len(episode), seed=10 + i)
        writer.write_episode(episode, frames[episode.episode_id])
    return writer, frames


def test_round_trip_episodes_frames_boxes(tmp_path):
    episodes = _episodes()
    writer, frames = _write_all(tmp_path, episodes)
    info = writer.finalize()
    assert info["num_episodes"] == 4 and info["num_frames"] == 17
    assert {s: v["episodes"] for s, v in info["splits"].items()} == {
        "train": 2,
        "test_seen": 1,
        "test_unseen": 1,
        "val": 0,  # every split gets its annotation file, empty when it holds nothing
    }
    assert info["splits"]["train"]["scenes"] == ["embedded-1"] and info["episodes_with_boxes"] == 3
    assert info["action_counts"]["9"] == 4 and info["stats_split"] == "train"
    store = FrameStore(tmp_path)
    for split in ("train", "test_seen", "test_unseen"):
        read = load_openfly_dataset(tmp_path, split, KEEP)
        expected = sorted((e for e in episodes if e.split == split), key=lambda e: e.episode_id)
        assert len(read) == len(expected)
        for got, want in zip(read, expected):
            assert_episodes_equal(got, want)
            for rgb, frame in zip(store.frames(got), frames[want.episode_id]):
                np.testing.assert_array_equal(rgb, frame)
    assert read[0].boxes is None  # released-like episode without boxes stays without
    assert read_annotation_pitch(tmp_path) == -45.0
    stats = json.loads((tmp_path / "meta/stats.json").read_text())
    assert stats == compute_action_statistics([e for e in episodes if e.split == "train"])
    data_files = json.loads((tmp_path / "meta/data_files.json").read_text())
    assert data_files["test_seen"] == ["traj/embedded-2/astar_data/low_average/traj_c.parquet"]


def read_annotation_pitch(root) -> float:
    records = json.loads((root / "Annotation/train.json").read_text())
    return records[0]["pitch_deg"]


def test_parquet_holds_the_episode(tmp_path):
    episode = _episodes()[1]
    writer, _ = _write_all(tmp_path, [episode])
    got = read_parquet_episode(writer.trajectory_path(episode.episode_id))
    assert_episodes_equal(got, episode)


def test_jpeg_frames_are_close(tmp_path):
    episode = _episodes()[0]
    _, frames = _write_all(tmp_path, [episode], image_format="jpeg")
    (got,) = load_openfly_dataset(tmp_path, "train", KEEP)
    rgb = FrameStore(tmp_path).frame(got, 0)
    assert rgb.shape == frames[episode.episode_id][0].shape  # lossy: only shape and rough content
    assert np.abs(rgb.astype(int) - frames[episode.episode_id][0]).mean() < 60


def test_datasets_streaming_over_written_files(tmp_path):
    datasets = pytest.importorskip("datasets")
    episodes = _episodes()
    writer, frames = _write_all(tmp_path, episodes)
    writer.finalize()
    files = sorted(str(p) for p in (tmp_path / "traj").rglob("*.parquet"))
    stream = datasets.load_dataset("parquet", data_files={"train": files}, split="train", streaming=True)
    rows = list(stream)
    assert len(rows) == 17
    by_episode = {e.episode_id: e for e in episodes}
    seen = {}
    for row in rows:
        episode = by_episode[row["episode_id"]]
        t = seen.setdefault(row["episode_id"], 0)
        seen[row["episode_id"]] += 1
        np.testing.assert_array_equal(np.asarray(row["image"].convert("RGB")), frames[episode.episode_id][t])
        assert row["action"] == episode.actions[t] and row["split"] == episode.split
        assert row["instruction"] == episode.instruction and row["scene_id"] == episode.scene_id
        if episode.boxes is not None and episode.box_visible[t]:
            assert row["box_visible"] and np.allclose(row["box"], episode.boxes[t])
        else:
            assert not row["box_visible"] and row["box"] is None
    non_streaming = datasets.load_dataset("parquet", data_files={"train": files}, split="train")
    assert non_streaming.features["image"].__class__.__name__ == "Image"
    assert len(non_streaming.filter(lambda r: r["split"] == "test_seen")) == 4


def test_resume_has_episode(tmp_path):
    episode = _episodes()[0]
    writer = OpenFlyDatasetWriter(tmp_path)
    assert not writer.has_episode(episode.episode_id)
    writer.write_episode(episode, make_frames(len(episode)))
    assert writer.has_episode(episode.episode_id)
    assert OpenFlyDatasetWriter(tmp_path).has_episode(episode.episode_id)  # a new process sees it too
    writer.write_episode(episode, make_frames(len(episode)))  # written again: replaced, not duplicated
    part = tmp_path / "Annotation/parts/train/embedded-1.json"
    assert len(json.loads(part.read_text())) == 1
    writer.trajectory_path(episode.episode_id).unlink()  # record without parquet (crash between the two)
    assert not OpenFlyDatasetWriter(tmp_path).has_episode(episode.episode_id)
    with pytest.raises(FileNotFoundError, match="no parquet file"):
        writer.finalize()
    info = writer.finalize(strict=False)
    assert info["num_episodes"] == 0


def test_moving_an_episode_to_another_split_drops_the_old_record(tmp_path):
    episode = _episodes()[0]
    writer = OpenFlyDatasetWriter(tmp_path)
    writer.write_episode(episode, make_frames(len(episode)))
    episode.split = "test_seen"
    writer.write_episode(episode, make_frames(len(episode)))
    info = writer.finalize()
    assert info["splits"]["train"]["episodes"] == 0 and info["splits"]["test_seen"]["episodes"] == 1


def test_shard_merge(tmp_path):
    episodes = _episodes()
    _write_all(tmp_path / "machine_a", episodes[:2])  # scene embedded-1
    _write_all(tmp_path / "machine_b", episodes[2:])  # scenes embedded-2, embedded-9
    merged = tmp_path / "merged"
    for shard in ("machine_a", "machine_b"):
        shutil.copytree(tmp_path / shard, merged, dirs_exist_ok=True)
    info = OpenFlyDatasetWriter(merged).finalize()
    assert info["num_episodes"] == 4 and info["scenes"] == ["embedded-1", "embedded-2", "embedded-9"]
    assert len(load_openfly_dataset(merged, "train", KEEP)) == 2
    # the same episode written on two machines under different part files is an error
    clash = merged / "Annotation/parts/train/embedded-1-copy.json"
    shutil.copy(merged / "Annotation/parts/train/embedded-1.json", clash)
    with pytest.raises(SchemaError, match="is also in"):
        OpenFlyDatasetWriter(merged).finalize()


def test_reading_parts_before_finalize(tmp_path, caplog):
    episodes = _episodes()
    _write_all(tmp_path, episodes)
    read = load_openfly_dataset(tmp_path, "train", KEEP)
    assert {e.episode_id for e in read} == {e.episode_id for e in episodes if e.split == "train"}
    assert "call OpenFlyDatasetWriter.finalize()" in caplog.text


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda e, f: setattr(e, "split", "validation"), "split"),
        (lambda e, f: f.pop(), "frames"),
        (lambda e, f: f.__setitem__(0, f[0][..., 0]), "frames"),
        (lambda e, f: e.boxes.__setitem__((0, 2), 1.5), "boxes"),
        (lambda e, f: e.actions.__setitem__(1, 0), "action"),
        (lambda e, f: setattr(e, "scene_id", "embedded-7"), "scene_id"),
    ],
)
def test_writer_rejects_bad_episodes_and_writes_nothing(tmp_path, change, field):
    episode = _episodes()[0]
    frames = make_frames(len(episode))
    change(episode, frames)
    with pytest.raises(SchemaError) as info:
        OpenFlyDatasetWriter(tmp_path).write_episode(episode, frames)
    assert info.value.field_name == field
    assert not any(tmp_path.rglob("*.parquet")) and not any(tmp_path.rglob("*.json"))


def test_part_files_roll_over_and_replace_in_place(tmp_path):
    ids = [f"embedded-1/astar_data/low_short/traj_{i}" for i in range(5)]
    episodes = [make_episode(eid, [9, 2, 0], "train", seed=i) for i, eid in enumerate(ids)]
    writer = OpenFlyDatasetWriter(tmp_path, part_max_records=2)
    for episode in episodes:
        writer.write_episode(episode, make_frames(len(episode)))
    folder = tmp_path / "Annotation/parts/train"
    sizes = {p.name: len(json.loads(p.read_text())) for p in folder.glob("*.json")}
    assert sizes == {"embedded-1.json": 2, "embedded-1.part-1.json": 2, "embedded-1.part-2.json": 1}
    episodes[0].instruction = "a new instruction"
    writer.write_episode(episodes[0], make_frames(3))  # rewritten: stays in the first part, no duplicate
    first = json.loads((folder / "embedded-1.json").read_text())
    assert len(first) == 2 and "a new instruction" in {r["gpt_instruction"] for r in first}
    reopened = OpenFlyDatasetWriter(tmp_path, part_max_records=2)  # a resumed process continues the last part
    assert all(reopened.has_episode(eid) for eid in ids)
    extra = make_episode("embedded-1/astar_data/low_short/traj_5", [9, 0], "train", seed=9)
    reopened.write_episode(extra, make_frames(2))
    assert len(json.loads((folder / "embedded-1.part-2.json").read_text())) == 2
    info = reopened.finalize()
    assert info["num_episodes"] == 6
    read = load_openfly_dataset(tmp_path, "train", KEEP)
    assert sorted(e.episode_id for e in read) == sorted(ids + [extra.episode_id])
    with pytest.raises(ValueError, match="part_max_records"):
        OpenFlyDatasetWriter(tmp_path, part_max_records=0)


def test_each_legs_goal_round_trips_and_a_broken_one_is_named(tmp_path):
    """`leg_goals` (a chained route's goal per leg) is written and read back exactly; a record whose legs do not
    match its targets, or whose goal is not 3 numbers, is refused naming the file, the record and the field."""
    episode = make_episode("embedded-1/astar_data/high_short/traj_a", [9, 2, 9, 1, 0], "train", seed=1)
    episode.landmark_ids = ["embedded-1/lm3", "embedded-1/lm7"]
    episode.leg_goals = np.array([[10.0, -4.5, 30.0], [22.25, 8.0, 31.5]])
    _write_all(tmp_path, [episode])[0].finalize()
    (read,) = load_openfly_dataset(tmp_path, "train", KEEP)
    assert_episodes_equal(read, episode)
    assert [g.tolist() for g in read.route_goals] == [[10.0, -4.5, 30.0], [22.25, 8.0, 31.5]]
    assert [g.tolist() for g in dataclasses.replace(read, leg_goals=None).route_goals] == [read.goal.tolist()]
    path = tmp_path / "Annotation" / "train.json"
    for broken, problem in (
        ({"leg_goals": [[10.0, -4.5, 30.0]]}, "1 legs for 2 landmark_ids"),
        ({"leg_goals": [[10.0, -4.5]]}, "3 finite numbers per leg"),
        ({"leg_goals": []}, "3 finite numbers per leg"),
    ):
        record = {**json.loads(path.read_text())[0], **broken}
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps([record]))
        with pytest.raises(SchemaError, match=problem) as info:
            read_annotation_file(bad, KEEP)
        assert (info.value.file, info.value.record, info.value.field_name) == (str(bad), 0, "leg_goals")

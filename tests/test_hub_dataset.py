"""Dataset release: folder layout, card `configs`, and `datasets.load_dataset` on the release folder."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from openfly_agent.hub.config import DatasetReleaseConfig
from openfly_agent.hub.dataset_release import build_dataset_release
from openfly_agent.hub.model_card import split_front_matter

CARD = """---
license: mit
task_categories:
- robotics
pretty_name: OpenFly embedded city
---

# OpenFly embedded city

Load it with `datasets.load_dataset("{{ repo_id }}")`.
"""
# split -> (annotation file, [(episode id, number of frames)])
EPISODES = {
    "train": (
        "train.json",
        [("embedded-1/astar_data/low_short/t0", 3), ("embedded-1/astar_data/high_long/t1", 4)],
    ),
    "test_seen": ("seen.json", [("embedded-1/astar_data/low_short/t2", 2)]),
    "test_unseen": ("unseen.json", [("embedded-9/astar_data/low_short/t3", 5)]),
}


def make_dataset_root(root: Path) -> Path:
    """A dataset root in the release layout: traj/**.parquet, Annotation/*.json (+ parts), meta/."""
    for split, (name, episodes) in EPISODES.items():
        records = []
        for episode_id, frames in episodes:
            table = pa.table(
                {
                    "frame_index": pa.array(range(frames), pa.int64()),
                    "pos": [[float(i), 0.0, 10.0] for i in range(frames)],
                    "yaw": [0.0] * frames,
                    "action_type": ["forward"] * frames,
                    "env_id": [episode_id.split("/")[0]] * frames,
                    "traj_id": [episode_id.split("/", 1)[1]] * frames,
                    "split": [split] * frames,
                }
            )
            path = root / "traj" / f"{episode_id}.parquet"
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, path)
            records.append(
                {"image_path": episode_id, "gpt_instruction": f"fly to {episode_id}", "action": [1] * frames}
            )
        (root / "Annotation").mkdir(parents=True, exist_ok=True)
        (root / "Annotation" / name).write_text(json.dumps(records))
    (root / "Annotation" / "parts" / "train").mkdir(parents=True)
    (root / "Annotation" / "parts" / "train" / "embedded-1.json").write_text("[]")
    (root / "meta").mkdir()
    (root / "meta" / "info.json").write_text(json.dumps({"num_episodes": 4}))
    (root / "meta" / "stats.json").write_text(json.dumps({}))
    return root


@pytest.fixture
def release(tmp_path):
    root = make_dataset_root(tmp_path / "data")
    card = tmp_path / "card.md"
    card.write_text(CARD)
    cfg = DatasetReleaseConfig(
        dataset_root=str(root),
        repo_id="me/openfly-embedded",
        card=str(card),
        output_dir=str(tmp_path / "rel"),
    )
    return build_dataset_release(cfg)


def test_release_folder_layout(release):
    files = sorted(str(p.relative_to(release)) for p in release.rglob("*") if p.is_file())
    assert files == sorted(
        [
            "README.md",
            "Annotation/train.json",
            "Annotation/seen.json",
            "Annotation/unseen.json",
            "meta/info.json",
            "meta/stats.json",
            *(f"traj/{eid}.parquet" for _, episodes in EPISODES.values() for eid, _ in episodes),
        ]
    )  # no Annotation/parts/: resumability bookkeeping stays local


def test_card_configs_and_size(release):
    from huggingface_hub import DatasetCard

    text = (release / "README.md").read_text()
    meta, body = split_front_matter(text)
    assert meta["license"] == "mit" and meta["task_categories"] == ["robotics"]  # template keys kept
    assert meta["size_categories"] == ["n<1K"]  # 14 frames
    [trajectories] = meta["configs"]
    assert trajectories["config_name"] == "trajectories" and trajectories["default"] is True
    assert {d["split"]: d["path"] for d in trajectories["data_files"]} == {
        split: sorted(f"traj/{eid}.parquet" for eid, _ in episodes)
        for split, (_, episodes) in EPISODES.items()
    }
    assert 'load_dataset("me/openfly-embedded")' in body
    DatasetCard(text, ignore_metadata_errors=False)


def test_load_dataset_reads_each_split(release, tmp_path):
    import datasets

    frames = datasets.load_dataset(str(release), cache_dir=str(tmp_path / "cache"))
    assert {split: ds.num_rows for split, ds in frames.items()} == {
        "train": 7,
        "test_seen": 2,
        "test_unseen": 5,
    }
    assert set(frames["test_unseen"]["split"]) == {"test_unseen"}
    assert sorted(set(frames["train"]["traj_id"])) == ["astar_data/high_long/t1", "astar_data/low_short/t0"]


def test_missing_trajectory_is_named(tmp_path):
    root = make_dataset_root(tmp_path / "data")
    (root / "traj" / "embedded-9/astar_data/low_short/t3.parquet").unlink()
    card = tmp_path / "card.md"
    card.write_text(CARD)
    cfg = DatasetReleaseConfig(
        dataset_root=str(root), repo_id="me/x", card=str(card), output_dir=str(tmp_path / "o")
    )
    with pytest.raises(FileNotFoundError, match=r"unseen.json: record 0: trajectory file .*t3.parquet"):
        build_dataset_release(cfg)


def test_existing_output_is_kept_without_overwrite(tmp_path, release):
    root = tmp_path / "data"
    cfg = DatasetReleaseConfig(
        dataset_root=str(root), repo_id="me/x", card=str(tmp_path / "card.md"), output_dir=str(release)
    )
    with pytest.raises(FileExistsError, match="--overwrite"):
        build_dataset_release(cfg)
    assert (release / "README.md").is_file()


def test_bad_repo_id_is_rejected():
    with pytest.raises(ValueError, match="namespace/name"):
        DatasetReleaseConfig(dataset_root="x", repo_id="no-namespace")

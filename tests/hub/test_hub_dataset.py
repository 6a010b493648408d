"""Dataset release: folder layout, card `configs`, and `datasets.load_dataset` on the release folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from data_factories import make_episode, make_frames  # tests/ is on sys.path (pytest prepend mode)

from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.hub.config import DatasetReleaseConfig
from openfly_agent.hub.dataset_release import build_dataset_release
from openfly_agent.hub.model_card import split_front_matter

CARD = Path(__file__).resolve().parents[2] / "data_cards" / "embedded.md"
# (episode id, actions, split): 14 frames in all, 6 + 5 in train
EPISODES = [
    ("embedded-1/astar_data/high_short/t0", [9, 2, 9, 1, 1, 0], "train"),
    ("embedded-1/astar_data/low_short/t1", [8, 3, 9, 4, 0], "train"),
    ("embedded-1/astar_data/low_short/t2", [1, 0], "test_seen"),
    ("embedded-9/astar_data/low_average/t3", [2, 0], "test_unseen"),
]
SPLIT_FILES = {"train": "train.json", "test_seen": "seen.json", "test_unseen": "unseen.json"}


def make_dataset_root(root: Path) -> tuple[Path, dict[str, list[np.ndarray]]]:
    """A finalized dataset written by the data package's writer; returns (root, frames per episode)."""
    writer = OpenFlyDatasetWriter(root)
    frames = {}
    for seed, (episode_id, actions, split) in enumerate(EPISODES):
        frames[episode_id] = make_frames(len(actions), seed=seed)
        writer.write_episode(make_episode(episode_id, actions, split, seed=seed), frames[episode_id])
    writer.finalize()
    return root, frames


def release_config(root: Path, out: Path, **changes) -> DatasetReleaseConfig:
    values = {"dataset_root": str(root), "repo_id": "me/openfly-embedded", "card": str(CARD)}
    return DatasetReleaseConfig(**{**values, "output_dir": str(out), **changes})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset_root(tmp_path_factory.mktemp("data") / "root")


@pytest.fixture(scope="module")
def release(dataset, tmp_path_factory):
    return build_dataset_release(release_config(dataset[0], tmp_path_factory.mktemp("rel") / "out"))


def test_release_folder_layout(release):
    files = sorted(str(p.relative_to(release)) for p in release.rglob("*") if p.is_file())
    expected = ["README.md", "meta/info.json", "meta/stats.json", "meta/data_files.json"]
    expected += [f"Annotation/{name}" for name in SPLIT_FILES.values()]
    expected += [f"traj/{episode_id}.parquet" for episode_id, _, _ in EPISODES]
    assert files == sorted(expected)  # no Annotation/parts/: resumability bookkeeping stays local


def test_card_configs_and_size(release):
    from huggingface_hub import DatasetCard

    text = (release / "README.md").read_text()
    meta, body = split_front_matter(text)
    assert meta["license"] == "mit" and meta["task_categories"] == ["robotics"]  # template keys kept
    assert meta["size_categories"] == ["n<1K"]
    [trajectories] = meta["configs"]
    assert trajectories["config_name"] == "trajectories" and trajectories["default"] is True
    assert {d["split"]: d["path"] for d in trajectories["data_files"]} == {
        "train": [
            "traj/embedded-1/astar_data/high_short/t0.parquet",
            "traj/embedded-1/astar_data/low_short/t1.parquet",
        ],
        "test_seen": ["traj/embedded-1/astar_data/low_short/t2.parquet"],
        "test_unseen": ["traj/embedded-9/astar_data/low_average/t3.parquet"],
    }
    assert 'load_dataset("me/openfly-embedded", split="train"' in body and "{{repo_id}}" not in body
    DatasetCard(text, ignore_metadata_errors=False)


def test_load_dataset_reads_each_split(release, dataset, tmp_path):
    import datasets

    frames = datasets.load_dataset(str(release), cache_dir=str(tmp_path / "cache"))
    assert {split: ds.num_rows for split, ds in frames.items()} == {
        "train": 11,
        "test_seen": 2,
        "test_unseen": 2,
    }
    unseen = frames["test_unseen"]
    assert set(unseen["split"]) == {"test_unseen"} and unseen["action"] == [2, 0]
    first = np.asarray(unseen[0]["image"].convert("RGB"))
    np.testing.assert_array_equal(first, dataset[1]["embedded-9/astar_data/low_average/t3"][0])  # pixel-exact


def test_missing_trajectory_is_named(tmp_path):
    root, _ = make_dataset_root(tmp_path / "data")
    (root / "traj/embedded-9/astar_data/low_average/t3.parquet").unlink()
    with pytest.raises(FileNotFoundError, match=r"unseen.json: record 0: trajectory file .*t3.parquet"):
        build_dataset_release(release_config(root, tmp_path / "out"))


def test_unfinalized_dataset_is_refused(tmp_path):
    root, _ = make_dataset_root(tmp_path / "data")
    (root / "meta/info.json").unlink()
    with pytest.raises(FileNotFoundError, match="finalize the dataset"):
        build_dataset_release(release_config(root, tmp_path / "out"))


def test_existing_output_is_kept_without_overwrite(dataset, release):
    with pytest.raises(FileExistsError, match="--overwrite"):
        build_dataset_release(release_config(dataset[0], release))
    assert (release / "README.md").is_file()


def test_bad_repo_id_is_rejected():
    with pytest.raises(ValueError, match="namespace/name"):
        DatasetReleaseConfig(dataset_root="x", repo_id="no-namespace")

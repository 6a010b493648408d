"""Data configs: the YAML files under configs/data parse, bad values get errors that say what to change."""

from __future__ import annotations

from pathlib import Path

import pytest
from data_factories import make_episode, make_frames

from openfly_agent.data.config import DataConfig, HistoryConfig
from openfly_agent.data.dataset import make_step_dataset
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.utils.config import load_yaml_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "data"


@pytest.mark.parametrize("name", ["embedded-small", "openfly_released"])
def test_yaml_configs_parse(name):
    cfg = load_yaml_config(
        DataConfig, CONFIGS / f"{name}.yaml", ["--history.mode=uniform", "--reader.strict=false"]
    )
    assert cfg.history.mode == "uniform" and cfg.reader.strict is False


def test_validation_reads_the_val_split_by_default_never_a_test_split():
    cfg = DataConfig()
    assert cfg.val_split == "val" and cfg.test_split == "test_unseen"


def test_bad_values_say_what_to_change():
    with pytest.raises(ValueError, match="data.test_split='validation'"):
        DataConfig(test_split="validation")
    with pytest.raises(ValueError, match="data.history.mode='latest'"):
        HistoryConfig(mode="latest")
    with pytest.raises(ValueError, match="num_workers=-1"):
        DataConfig(num_workers=-1)


def test_make_step_dataset(tmp_path):
    episode = make_episode("embedded-1/astar_data/low_short/a", [-1, 9, 2, 0, -2])
    writer = OpenFlyDatasetWriter(tmp_path)
    writer.write_episode(episode, make_frames(len(episode)))
    writer.finalize()
    cfg = DataConfig(root=str(tmp_path), history=HistoryConfig(mode="uniform"))
    dataset = make_step_dataset(cfg, "train", capacity=2, set_size=5)  # trim (default): 9, 2, 0
    assert (
        len(dataset) == 3
        and dataset[0]["action"] == 9
        and dataset.episodes[0].frame_ids == episode.frame_ids[1:4]
    )

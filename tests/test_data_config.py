"""Data configs: the YAML files under configs/data parse, bad values get errors that say what to change."""

from __future__ import annotations

from pathlib import Path

import pytest
from data_factories import make_episode, make_frames

from openfly_agent.data.config import DataConfig, HistoryConfig
from openfly_agent.data.dataset import make_step_dataset
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.utils.config import load_yaml_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "data"


@pytest.mark.parametrize("name", ["embedded", "openfly_released"])
def test_yaml_configs_parse(name):
    cfg = load_yaml_config(
        DataConfig, CONFIGS / f"{name}.yaml", ["--history.mode=uniform", "--reader.strict=false"]
    )
    assert cfg.history.mode == "uniform" and cfg.reader.strict is False and cfg.history.capacity == 2


def test_bad_values_say_what_to_change():
    with pytest.raises(ValueError, match="DataConfig.split='val'"):
        DataConfig(split="val")
    with pytest.raises(ValueError, match="capacity=-1"):
        HistoryConfig(capacity=-1)
    with pytest.raises(ValueError, match="set_size=0"):
        HistoryConfig(set_size=0)


def test_make_step_dataset(tmp_path):
    episode = make_episode("embedded-1/astar_data/low_short/a", [-1, 9, 2, 0, -2])
    writer = OpenFlyDatasetWriter(tmp_path)
    writer.write_episode(episode, make_frames(len(episode)))
    writer.finalize()
    cfg = DataConfig(root=str(tmp_path), history=HistoryConfig(mode="uniform"))
    dataset = make_step_dataset(cfg)  # trim (default): 3 steps 9, 2, 0
    assert (
        len(dataset) == 3
        and dataset[0]["action"] == 9
        and dataset.episodes[0].frame_ids == episode.frame_ids[1:4]
    )

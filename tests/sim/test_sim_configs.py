"""The YAML configs under configs/sim parse into EmbeddedSimConfig and round-trip through draccus."""

from pathlib import Path

import pytest

from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.utils.config import config_from_dict, config_to_dict, load_yaml_config

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs" / "sim").glob("embedded*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_parses_and_round_trips(path):
    cfg = load_yaml_config(EmbeddedSimConfig, path, overrides=["--collision=count"])
    assert isinstance(cfg, EmbeddedSimConfig) and cfg.collision == "count"
    assert config_from_dict(EmbeddedSimConfig, config_to_dict(cfg)) == cfg


def test_defaults_match_the_reference_yaml():
    assert len(CONFIGS) == 2
    assert load_yaml_config(EmbeddedSimConfig, CONFIGS[0]) == EmbeddedSimConfig()

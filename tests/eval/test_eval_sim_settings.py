"""eval/factory.py: the embedded simulator rebuilds a generated dataset's cities at its frame size, from the
dataset's generation settings (the typed record, or the toolchain config of a dataset generated before it)."""

from __future__ import annotations

import json

from openfly_agent import constants as C
from openfly_agent.data.generation_settings import GenerationSettings
from openfly_agent.eval.config import EmbeddedSimSettings, EvalConfig
from openfly_agent.eval.factory import embedded_sim_config


def _sim(root, **sim):
    cfg = EvalConfig(policy="random", dataset_root=str(root), sim=EmbeddedSimSettings(**sim))
    made = embedded_sim_config(cfg, episodes=[])
    return made.width, made.height, made.city.size_m, made.city.n_buildings, made.voxel_size


def test_the_simulator_takes_the_datasets_frame_size_and_cities(tmp_path):
    GenerationSettings(width=64, height=48, city_size_m=300.0, city_buildings=20).save(tmp_path / "new")
    older = tmp_path / "old" / C.TOOLCHAIN_CONFIG_JSON  # generated before the record: the full config only
    older.parent.mkdir(parents=True)
    config = {"render": {"width": 64, "height": 48}, "scenes": {"city_size_m": 300.0, "city_buildings": 20}}
    older.write_text(json.dumps(config))
    assert _sim(tmp_path / "new") == _sim(tmp_path / "old") == (64, 48, 300.0, 20, 2.0)
    assert _sim(tmp_path / "new", width=96, height=80)[:2] == (96, 80)  # the options win

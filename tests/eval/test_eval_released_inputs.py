"""`eval.py` on released-format data: scenes its simulator cannot fly and malformed records, each one line and
exit 2 before a model loads."""

from __future__ import annotations

import json

import pytest
from data_factories import make_episode, make_frames

from openfly_agent import constants as C
from openfly_agent.data.writer import OpenFlyDatasetWriter


def _released_format_dataset(root) -> None:
    writer = OpenFlyDatasetWriter(root)
    for k, scene in enumerate(["env_airsim_16", "env_airsim_16", "env_ue_smallcity"]):
        episode = make_episode(f"{scene}/astar_data/low_short/ep{k}", [1, 2, 0], split=C.SPLIT_TEST_SEEN)
        writer.write_episode(episode, make_frames(len(episode)))
    writer.finalize()


def test_embedded_simulator_refuses_a_released_scene_before_loading_the_model(tmp_path, capsys, monkeypatch):
    """The default `--sim.type=embedded` on AirSim / UE episodes: exit 2, one line naming the scene and the
    bridges, no model loaded and no output folder made."""
    from eval_helpers import eval_main

    import openfly_agent.eval.factory as factory

    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded")

    monkeypatch.setattr(factory, "load_agent", no_model)
    dataset, out, checkpoint = tmp_path / "data", tmp_path / "out", tmp_path / "ckpt"
    _released_format_dataset(dataset)
    checkpoint.mkdir()
    (checkpoint / "config.json").write_text(json.dumps({"model_type": "openfly_agent"}))
    argv = [
        "--checkpoint", str(checkpoint), f"--split=[{C.SPLIT_TEST_SEEN}]", "--progress=false",
        f"--dataset_root={dataset}", f"--output_dir={out}",
    ]  # fmt: skip
    assert eval_main()(argv) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    # episodes are evaluated sorted by id: ep0 (env_airsim_16) first; all 3 are in real scenes
    assert line.startswith(
        "eval.py: --sim.type=embedded flies only the embedded cities (scene ids embedded-<seed>); episode scene "
        "'env_airsim_16' (3 of 3 episodes are not embedded) needs a bridge: --sim.type=unrealcv|airsim|gs_http "
        "(this one: --sim.type=airsim)"
    ), line
    assert not out.exists()


def test_a_strict_read_names_the_option_that_skips_malformed_records(tmp_path, openfly_fixtures):
    from openfly_agent.data.config import ReaderOptions
    from openfly_agent.data.schema import SchemaError
    from openfly_agent.eval.config import EvalConfig
    from openfly_agent.eval.factory import load_full_splits

    records = json.loads((openfly_fixtures / "eval_test.json").read_text())[:3]
    records[1]["action"].append(-2)  # one entry too long: the action list is named, not index_list
    (tmp_path / C.DATASET_ANNOTATION_DIR).mkdir()
    (tmp_path / C.DATASET_ANNOTATION_DIR / "seen.json").write_text(json.dumps(records))
    cfg = EvalConfig(policy="stop", dataset_root=str(tmp_path), split=[C.SPLIT_TEST_SEEN])
    with pytest.raises(SchemaError) as info:
        load_full_splits(cfg)
    assert (info.value.record, info.value.field_name) == (1, "action")
    assert str(info.value).endswith("--reader.strict=false skips each one, logged and counted)")
    cfg.reader = ReaderOptions(strict=False)
    assert len(load_full_splits(cfg)[C.SPLIT_TEST_SEEN]) == 2

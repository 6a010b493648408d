"""The toolchain command line and its shipped configs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from openfly_agent.toolchain.__main__ import main
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.utils.config import load_yaml_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "toolchain"


@pytest.mark.parametrize("name", ["embedded-small", "embedded-100k"])
def test_shipped_configs_load_and_keep_unseen_scenes_apart(name):
    cfg = load_yaml_config(GenerateConfig, CONFIGS / f"{name}.yaml")
    assert not set(cfg.scenes.train_seeds) & set(cfg.scenes.unseen_seeds)
    assert cfg.instructions.backend == "template" and cfg.workers >= 1
    attempts = cfg.scenes.trajectories_per_scene * (
        len(cfg.scenes.train_seeds) + len(cfg.scenes.unseen_seeds)
    )
    assert (800 <= attempts <= 2000) if name == "embedded-small" else attempts >= 100_000


@pytest.mark.parametrize("name", ["embedded-small-extra", "embedded-small-cities"])
def test_extra_train_configs_add_train_routes_only_and_never_touch_a_test_city(name):
    small = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small.yaml")
    extra = load_yaml_config(GenerateConfig, CONFIGS / f"{name}.yaml")
    assert extra.output_dir != small.output_dir and extra.seed != small.seed  # other routes, own root
    assert extra.scenes.unseen_seeds == [] and extra.scenes.test_seen_fraction == 0.0  # train split only
    assert not set(extra.scenes.train_seeds) & set(small.scenes.unseen_seeds)
    assert (extra.render, extra.route, extra.map) == (small.render, small.route, small.map)  # same task


def test_the_second_unseen_split_uses_cities_no_other_config_trains_or_tests_on():
    held_out = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small-unseen-more.yaml")
    assert held_out.scenes.train_seeds == [] and held_out.scenes.unseen_seeds
    others = ["embedded-small", "embedded-small-extra", "embedded-small-cities"]
    for name in others:
        cfg = load_yaml_config(GenerateConfig, CONFIGS / f"{name}.yaml")
        used = set(cfg.scenes.train_seeds) | set(cfg.scenes.unseen_seeds)
        assert not used & set(held_out.scenes.unseen_seeds), name
        assert (held_out.render, held_out.route, held_out.map) == (cfg.render, cfg.route, cfg.map), name


def test_the_second_validation_set_holds_val_routes_only_in_cities_no_other_config_uses():
    val_more = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small-val-more.yaml")
    scenes = val_more.scenes
    assert scenes.train_seeds == [] and scenes.unseen_seeds == [] and scenes.test_seen_fraction == 0.0
    assert len(scenes.val_seeds) == 4 and scenes.val_unseen_per_scene == 65  # 260 routes
    small = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small.yaml")
    assert (val_more.render, val_more.route, val_more.map) == (
        small.render,
        small.route,
        small.map,
    )  # same task
    for path in sorted(CONFIGS.glob("*.yaml")):
        if path.name == "embedded-small-val-more.yaml":
            continue
        other = load_yaml_config(GenerateConfig, path).scenes
        used = set(other.train_seeds) | set(other.unseen_seeds) | set(other.val_seeds)
        assert not used & set(scenes.val_seeds), path.name


def test_the_second_validation_set_generates_a_val_split_and_nothing_else(tmp_path, capsys):
    """The shipped config, shortened to one city and 2 routes: its routes land in val.json, the other splits are
    empty."""
    config = str(CONFIGS / "embedded-small-val-more.yaml")
    overrides = ["--scenes.val_seeds=[1006]", "--scenes.val_unseen_per_scene=2", "--workers=0"]
    assert main(["generate", "--config_path", config, f"--output_dir={tmp_path}", *overrides]) == 0
    counts = {name: len(json.loads((tmp_path / "Annotation" / name).read_text())) for name in
              ("train.json", "seen.json", "unseen.json", "val.json")}  # fmt: skip
    assert counts == {"train.json": 0, "seen.json": 0, "unseen.json": 0, "val.json": 2}


def test_the_validation_city_is_a_city_of_no_other_split_of_any_shipped_dataset():
    for name in ("embedded-small", "embedded-100k"):
        cfg = load_yaml_config(GenerateConfig, CONFIGS / f"{name}.yaml")
        assert (
            cfg.scenes.val_seeds and cfg.scenes.val_seen_per_scene > 0 and cfg.scenes.val_unseen_per_scene > 0
        )
        for path in sorted(CONFIGS.glob("*.yaml")):
            other = load_yaml_config(GenerateConfig, path)
            used = set(other.scenes.train_seeds) | set(other.scenes.unseen_seeds)
            assert not used & set(cfg.scenes.val_seeds), (name, path.name)


def test_a_plain_generate_is_exactly_the_default_dataset_config(capsys):
    """No --config: the command resolves to configs/toolchain/embedded-small.yaml, the dataset train.py reads."""
    from openfly_agent.toolchain.__main__ import _parse_generate
    from openfly_agent.training.cli import parse_args

    shipped = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small.yaml")
    assert _parse_generate([]) == shipped
    assert _parse_generate(["--workers=0"]) == load_yaml_config(
        GenerateConfig, CONFIGS / "embedded-small.yaml", ["--workers=0"]
    )
    data = parse_args([]).data  # train.py's default dataset is that one
    assert data.root == shipped.output_dir
    assert main(["generate", "--help"]) == 0
    assert "embedded-small.yaml" in capsys.readouterr().out


def test_config_overrides():
    cfg = load_yaml_config(
        GenerateConfig, CONFIGS / "embedded-small.yaml", ["--shard=1/4", "--render.width=96"]
    )
    assert cfg.shard == "1/4" and cfg.render.width == 96


def test_bad_config_values_name_the_field(capsys):
    config = str(CONFIGS / "embedded-small.yaml")
    assert main(["generate", "--config_path", config, "--instructions.backend=gpt"]) == 2
    assert "instructions.backend must be 'template' or 'vlm'" in capsys.readouterr().err
    assert main(["generate", "--config_path", config, "--route.chain_prob=2"]) == 2
    assert "route.chain_prob must be a probability" in capsys.readouterr().err


def test_unknown_command_is_one_line_naming_the_commands(capsys):
    assert main(["train"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'train'" in err and "choose one of generate, summarize" in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("command", ["dagger-round", "dagger"])
def test_a_missing_checkpoint_is_one_line_naming_it(command, tmp_path, capsys):
    missing = str(tmp_path / "run" / "navigation")
    args = [command, f"--checkpoint={missing}", f"--output_dir={tmp_path / 'out'}"]
    if command == "dagger-round":
        args.append(f"--source_root={tmp_path / 'data'}")
    else:
        args += ["--config_path", str(CONFIGS / "embedded-small.yaml")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"--checkpoint {missing!r}" in err and "Traceback" not in err


def test_the_long_benchmark_turns_sharply_and_names_the_passed_landmark(capsys):
    """embedded-long adopts the two levers that raised its hidden share (data_cards/embedded-long.md);
    embedded-small keeps both off. The passed-landmark phrasing is the template's, so the VLM backend refuses it."""
    long = load_yaml_config(GenerateConfig, CONFIGS / "embedded-long.yaml")
    small = load_yaml_config(GenerateConfig, CONFIGS / "embedded-small.yaml")
    assert long.route.chain_bearing_deg == [90.0, 150.0] and long.instructions.name_passed_landmark
    assert small.route.chain_bearing_deg == [30.0, 150.0] and not small.instructions.name_passed_landmark
    # each frame's box is its leg's target on the long routes; embedded-small keeps the released labels
    assert long.render.box_target == "leg" and small.render.box_target == "final"
    # choices on the long routes are made on a val split of their own, as on embedded-small
    assert long.scenes.val_seeds == [900]
    assert long.scenes.val_seen_per_scene > 0 and long.scenes.val_unseen_per_scene > 0
    config = str(CONFIGS / "embedded-long.yaml")
    assert main(["generate", "--config_path", config, "--instructions.backend=vlm"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "instructions.name_passed_landmark is a template option" in lines[0]

"""The adopted tiny model is one file (configs/model/tiny-adopted.yaml) that the recipes lay over their train
config; a stage's own train.py settings are a typed mapping (`overrides`), checked against TrainConfig when the
recipe is loaded, never a list of command-line strings."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from openfly_agent.recipe import RecipeConfig, StageBudget, recipe_steps
from openfly_agent.recipe import run as recipe_run
from openfly_agent.recipe.__main__ import main as recipe_main
from openfly_agent.recipe.config import stage_train_config
from openfly_agent.recipe.run import KIND_TRAIN
from openfly_agent.training.config import TrainConfig
from openfly_agent.utils.config import REPO_ROOT, config_to_dict, load_yaml_config, resolve_config_path

RECIPES = REPO_ROOT / "configs" / "recipe"
ADOPTED = "configs/model/tiny-adopted.yaml"
# every recipe built on the adopted one (tiny-recipe.yaml): all but the main job and the arm without grounding
ADOPTED_RECIPES = sorted(
    p.relative_to(RECIPES).as_posix()
    for p in RECIPES.rglob("*.yaml")
    if p.name not in ("main_job.yaml", "no_grounding_loss.yaml")
)


def _stages(cfg: RecipeConfig) -> dict[str, StageBudget]:
    return {
        "grounding": cfg.grounding,
        "navigation": cfg.navigation,
        "dagger.train": cfg.dagger.train,
        "rl": cfg.rl,
    }


def _recipe(name: str) -> RecipeConfig:
    return load_yaml_config(RecipeConfig, RECIPES / name, [])


def test_no_recipe_yaml_lists_train_options_as_strings():
    """An `args:` list of `--model...` strings is checked only when a subprocess parses it: none may remain."""
    found = []
    for path in sorted(RECIPES.rglob("*.yaml")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if re.match(r"\s*args\s*:", code) or "--" in code:
                found.append(f"{path.relative_to(REPO_ROOT)}:{number}: {line.strip()}")
    assert len(ADOPTED_RECIPES) >= 13 and not found, found


@pytest.mark.parametrize("name", ADOPTED_RECIPES)
def test_every_stage_of_an_adopted_recipe_trains_the_model_of_one_file(name):
    cfg = _recipe(name)
    assert cfg.model == ADOPTED
    for stage_name, stage in _stages(cfg).items():
        model = stage_train_config(cfg, stage, stage_name).model
        switches = (
            model.grounding.attribute_weight,
            model.vision.cnn_colour_stats,
            model.grounding.visual_skip,
        )
        assert switches == (1.0, True, True), (name, stage_name)  # those of configs/model/tiny-adopted.yaml


def test_the_recipe_stages_resolve_to_the_settings_they_were_measured_with():
    cfg = _recipe("tiny-recipe.yaml")
    grounding = stage_train_config(cfg, cfg.grounding, "grounding")
    navigation = stage_train_config(cfg, cfg.navigation, "navigation")
    dagger = stage_train_config(cfg, cfg.dagger.train, "dagger.train")
    assert (grounding.data.instruction_fraction, grounding.optim.ema_decay) == (0.75, 0.999)
    assert navigation.optim.ema_decay is None  # the weight average is the grounding stage's only
    assert navigation.optim.lr == 1e-3  # configs/train/tiny.yaml's
    assert dagger.optim.lr == 1e-4  # the round's: the navigation stage's final lr
    # an ablation arm keeps its own train config's memory under the adopted model
    arm = _recipe("ablations/current_frame.yaml")
    current = stage_train_config(arm, arm.navigation, "navigation")
    assert (current.model.memory.capacity, current.model.merging.enabled, current.data.history.mode) == (
        0,
        False,
        "none",
    )
    assert current.model.grounding.visual_skip is True
    # the arm without grounding is not the adopted model
    bare = _recipe("ablations/no_grounding_loss.yaml")
    assert bare.model is None
    for stage_name in ("navigation", "dagger.train"):
        model = stage_train_config(bare, _stages(bare)[stage_name], stage_name).model
        assert (model.grounding.has_head, model.vision.cnn_colour_stats) == (False, True)


def test_the_adopted_train_config_trains_the_recipe_model():
    """configs/train/tiny-adopted.yaml: configs/train/tiny.yaml with the adopted model, as one train.py run."""
    alone = config_to_dict(load_yaml_config(TrainConfig, REPO_ROOT / "configs/train/tiny-adopted.yaml", []))
    tiny = config_to_dict(load_yaml_config(TrainConfig, REPO_ROOT / "configs/train/tiny.yaml", []))
    cfg = _recipe("tiny-recipe.yaml")
    recipe_model = config_to_dict(stage_train_config(cfg, cfg.navigation, "navigation"))["model"]
    assert alone["model"] == recipe_model != tiny["model"]
    assert {k: v for k, v in alone.items() if k not in ("model", "output_dir")} == {
        k: v for k, v in tiny.items() if k not in ("model", "output_dir")
    }


def test_the_model_file_and_the_overrides_reach_the_stage_command_as_train_options():
    cfg = RecipeConfig(
        model=ADOPTED,
        navigation=StageBudget(
            steps=10,
            overrides={
                "data": {"extra_train_roots": ["a", "b"]},
                "gradient_checkpointing": True,
                "epochs": None,
            },
        ),
    )
    step = next(s for s in recipe_steps(cfg) if s.name == "navigation")
    assert Path(step.command[-4].removeprefix("--model=")).resolve() == (REPO_ROOT / ADOPTED).resolve()
    assert step.command[-3:] == [
        "--data.extra_train_roots=[a,b]",
        "--gradient_checkpointing=true",
        "--epochs=null",
    ]
    resolved = stage_train_config(cfg, cfg.navigation, "navigation")
    assert (resolved.data.extra_train_roots, resolved.gradient_checkpointing, resolved.epochs) == (
        ["a", "b"],
        True,
        None,
    )


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["--navigation.overrides={optim: {lrr: 1.0}}"],
            "navigation.overrides: train.py: unknown option --optim.lrr; did you mean --optim.lr?",
        ),
        (
            ["--dagger.train.overrides={optim: {lr: abc}}"],
            "dagger.train.overrides: train.py: --optim.lr: expected a float, got 'abc'",
        ),
        (["--model=configs/model/tiny-adopted.yml"], "model=configs/model/tiny-adopted.yml: no such file"),
    ],
)
def test_a_bad_stage_override_is_one_line_at_load_before_any_command_runs(args, line, monkeypatch, capsys):
    def no_command(*_args, **_kwargs):
        raise AssertionError("a stage command ran")

    monkeypatch.setattr(recipe_run, "start_group", no_command)
    assert recipe_main(["--config_path", str(RECIPES / "tiny-recipe.yaml"), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and line in err, err


def test_the_main_job_lays_its_one_model_file_over_both_stages_and_nothing_else():
    cfg = _recipe("main_job.yaml")
    assert cfg.model == "configs/model/tiny-main-job.yaml"
    train_steps = [step for step in recipe_steps(cfg) if step.kind == KIND_TRAIN]
    assert [step.name for step in train_steps] == ["grounding", "navigation"]
    for step in train_steps:
        model_args = [arg for arg in step.command if arg.startswith("--model")]
        assert model_args == [f"--model={resolve_config_path(cfg.model)}"], step.command
    section = yaml.safe_load(resolve_config_path(cfg.model).read_text())
    assert section == {"grounding": {"colour_vocabulary": True}}

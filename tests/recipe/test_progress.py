"""Steps, not minutes: the shipped recipes train fixed step counts, and a stage its time guard cut short says so
in the header of the table the recipe prints."""

from __future__ import annotations

import json
import re

import pytest
from eval_helpers import generate_tiny_dataset

from openfly_agent.recipe import DaggerSettings, RecipeConfig, StageBudget, recipe_steps
from openfly_agent.recipe import run as recipe_run
from openfly_agent.recipe.__main__ import main as recipe_main
from openfly_agent.recipe.progress import budget_header, stage_progress
from openfly_agent.recipe.run import KIND_TRAIN
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.state import TrainerState
from openfly_agent.utils.config import REPO_ROOT, load_yaml_config

SMALL_DATA = {  # train.py settings of the stage (its `overrides`)
    "batch": {"global_batch_size": 4, "per_device_batch_size": 2},
    "validation": {"interval": 0, "final_max_samples": 4},
    "logging": {"tracker": "none"},
    "checkpoint": {"save_interval": 0},
}


def _train_flags(cfg: RecipeConfig) -> dict[str, tuple[str, str]]:
    """stage name -> (--steps, --optim.horizon) of its train.py command."""
    flags = {}
    for step in recipe_steps(cfg):
        if step.kind == KIND_TRAIN:
            values = dict(
                a.removeprefix("--").split("=", 1) for a in step.command if a.startswith("--") and "=" in a
            )
            flags[step.name] = (values["steps"], values["optim.horizon"])
    return flags


def test_the_main_job_trains_the_steps_of_the_readme_table_with_a_generous_guard():
    cfg = load_yaml_config(RecipeConfig, REPO_ROOT / "configs/recipe/main_job.yaml", [])
    assert _train_flags(cfg) == {"grounding": ("1400", "steps"), "navigation": ("3036", "steps")}
    # the guard: 3x the reference machine's 6 + 12 minutes, times the colour vocabulary's step cost (1.08, 1.14)
    assert (cfg.grounding.minutes, cfg.navigation.minutes) == (20.0, 41.0)
    recipe = load_yaml_config(RecipeConfig, REPO_ROOT / "configs/recipe/tiny-recipe.yaml", [])
    assert _train_flags(recipe) == {"grounding": ("15183", "steps"), "navigation": ("19020", "steps")}
    readme = (REPO_ROOT / "README.md").read_text()
    assert "1,400" in readme and "3,036" in readme, "the README states the main job's steps"


def test_a_stage_the_guard_cut_short_is_named_in_the_printed_header(tmp_path, monkeypatch, capsys):
    data = tmp_path / "data"
    generate_tiny_dataset(data)
    cfg = RecipeConfig(
        output_dir=str(tmp_path / "run"), dataset_root=str(data), processes=1, torch_threads=1,
        grounding=StageBudget(steps=0), navigation=StageBudget(steps=100_000, minutes=0.05, overrides=SMALL_DATA),
        dagger=DaggerSettings(rounds=0),
    )  # fmt: skip
    navigation = [s for s in recipe_steps(cfg) if s.kind == KIND_TRAIN]
    monkeypatch.setattr(recipe_run, "recipe_steps", lambda _: navigation)  # train only: no dataset, no eval
    args = [f"--output_dir={cfg.output_dir}", f"--dataset_root={data}", "--processes=1", "--torch_threads=1"]
    args += ["--grounding.steps=0", "--navigation.steps=100000", "--navigation.minutes=0.05"]
    args += [f"--navigation.overrides={json.dumps(SMALL_DATA)}", "--dagger.rounds=0"]
    assert recipe_main(args) == 0
    reached = TrainerState.load(CheckpointManager(tmp_path / "run" / "navigation", keep_last=1).latest()).step
    assert 1 <= reached < 100_000
    printed = capsys.readouterr().out
    assert "**Cut short**: 1 training stage(s) stopped at the time guard" in printed
    line = re.search(r"- navigation: .*", printed).group(0)
    assert line == (
        f"- navigation: {reached:,} of 100,000 steps (its 0.05-minute guard stopped it): this machine is slower "
        "than the reference; expect lower SR"
    )
    assert printed.strip() == (tmp_path / "run" / "summary.md").read_text().strip()
    # the same run, had its budget been the steps it reached: no warning
    full = RecipeConfig(
        output_dir=cfg.output_dir, dataset_root=str(data), grounding=StageBudget(steps=0),
        navigation=StageBudget(steps=reached), dagger=DaggerSettings(rounds=0),
    )  # fmt: skip
    assert budget_header(stage_progress(full)) == (
        f"Every training stage ran its full number of steps.\n\n- navigation: {reached:,} of {reached:,} steps\n"
    )


@pytest.mark.parametrize("done", [3036, 1682])
def test_the_header_counts_with_thousands_separators(done):
    from openfly_agent.recipe.progress import StageProgress

    text = StageProgress("navigation", done, 3036, 36.0).describe()
    assert text.startswith(f"navigation: {done:,} of 3,036 steps")
    assert ("slower than the reference" in text) == (done < 3036)

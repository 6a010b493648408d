"""Every shipped recipe config runs end to end through `python -m openfly_agent.recipe`, shortened.

Each stage the config has runs (dataset, extra routes, grounding data, grounding, navigation, DAgger rounds, the
RL stage, evaluation with its more cities), shortened by `short_args`: the small generated dataset of the training
tests for every dataset the recipe generates, 2 steps per training stage (1 RL update), 2 episodes per evaluation.
The ablations share one representative (they change the train config only). Minutes each: marked slow.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import yaml

from openfly_agent.recipe.config import RecipeConfig
from openfly_agent.utils.config import REPO_ROOT, load_yaml_config
from openfly_agent.utils.processes import run_group

RECIPES = ["main_job.yaml", "tiny-recipe.yaml", "tiny-recipe-rl.yaml", "ablations/uniform_history.yaml"]
# the RL stage's settings of a shortened run (its `overrides`): 1 update of 2 episodes x 2 rollouts of <= 6 steps
SHORT_RL = "{optim: {lr: 1.0e-5, schedule: constant}, rl: {group_size: 2, episodes_per_update: 2, max_steps: 6, num_envs: 2}}"
TINY_DATASET_YAML = REPO_ROOT / "tests" / "training" / "tiny_dataset.yaml"


def _small_toolchain_config(folder: Path, name: str, cities: int = 0, val: bool = False) -> Path:
    """The training tests' small dataset YAML, writing into `folder / name`, its cities' seeds shifted by `cities`
    (a recipe's extra datasets hold other cities than its dataset); `val`: with a val split (2 routes per train
    city), for a recipe that evaluates val."""
    settings = yaml.safe_load(TINY_DATASET_YAML.read_text())
    scenes = settings["scenes"]
    scenes.update(
        train_seeds=[seed + cities for seed in scenes["train_seeds"]],
        unseen_seeds=[seed + cities for seed in scenes["unseen_seeds"]],
    )
    if val:
        scenes["val_seen_per_scene"] = 2
    settings.update(output_dir=str(folder / name), workers=0)
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


def short_args(cfg: RecipeConfig, folder: Path) -> list[str]:
    """The recipe's overrides that make it short: small datasets, 2 steps per stage, 2 episodes per split."""
    extras = [
        _small_toolchain_config(folder, f"extra{k}", 10 * (k + 1))
        for k in range(len(cfg.extra_toolchain_configs))
    ]
    cities = [
        _small_toolchain_config(folder, f"cities{k}", 100 * (k + 1)) for k in range(len(cfg.eval.more_cities))
    ]
    return [
        f"--output_dir={folder / 'recipe'}",
        f"--dataset_root={folder / 'dataset'}",
        f"--toolchain_config={_small_toolchain_config(folder, 'dataset', val='val' in cfg.eval.splits)}",
        f"--grounding_root={folder / 'grounding'}",
        f"--extra_toolchain_configs=[{','.join(map(str, extras))}]",
        f"--eval.more_cities=[{','.join(map(str, cities))}]",
        "--eval.max_episodes=2",
        "--eval.batch_size=2",
        "--grounding.steps=2",
        "--navigation.steps=2",
        "--dagger.train.steps=2",
        "--dagger.episodes=2",
        "--dagger.num_envs=2",
        *(["--rl.steps=1", f"--rl.overrides={SHORT_RL}"] if cfg.rl.steps else []),
    ]


@pytest.mark.slow
@pytest.mark.parametrize("config", RECIPES)
def test_a_shipped_recipe_runs_every_stage(config, tmp_path):
    path = REPO_ROOT / "configs" / "recipe" / config
    cfg = load_yaml_config(RecipeConfig, path)
    command = [
        sys.executable,
        "-m",
        "openfly_agent.recipe",
        "--config_path",
        str(path),
        *short_args(cfg, tmp_path),
    ]
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO_ROOT),
        "HF_HUB_OFFLINE": "1",
        "TOKENIZERS_PARALLELISM": "false",
    }
    result = run_group(command, timeout=1800, cwd=tmp_path, env=env)  # on timeout its runs are killed too
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    assert (tmp_path / "recipe" / "eval").is_dir()
    assert (tmp_path / "recipe" / "navigation" / "checkpoints" / "last").resolve().name.startswith("step-")
    if (
        cfg.rl.steps
    ):  # the RL agent evaluated, the agent it started from too, and the two paired in the report
        assert (tmp_path / "recipe" / "rl" / "checkpoints" / "last").resolve().name == "step-000001"
        assert (tmp_path / "recipe" / "eval_before_rl" / "agent" / "episodes.jsonl").is_file()
        assert (tmp_path / "recipe" / "eval_before_rl-cities0" / "agent" / "episodes.jsonl").is_file()
        summary = (tmp_path / "recipe" / "summary.md").read_text()
        assert "## rl\n\nagent - agent_before_rl" in summary and "| test_unseen / `standard` | 2 |" in summary
        assert "| all unseen / `standard` | 4 |" in summary  # test_unseen and the city's, 2 episodes each

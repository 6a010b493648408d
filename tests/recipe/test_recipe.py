"""The recipe's chain of commands and its resumable runner."""

from __future__ import annotations

import os
import signal
import sys

import pytest

from openfly_agent.recipe import (
    DaggerSettings,
    EvalSettings,
    RecipeConfig,
    StageBudget,
    recipe_steps,
    run_recipe,
)
from openfly_agent.recipe import run as recipe_run
from openfly_agent.recipe.__main__ import EXIT_TERMINATED
from openfly_agent.recipe.__main__ import main as recipe_main
from openfly_agent.recipe.run import DONE_MARKER, KIND_DATA, KIND_EVAL, KIND_TRAIN, RecipeStep
from openfly_agent.utils.config import REPO_ROOT, load_yaml_config, resolve_config_path
from openfly_agent.utils.processes import start_group


def _flag(command: list[str], name: str) -> str | None:
    """The value of `--name=value` or `--name value` in a command."""
    for i, arg in enumerate(command):
        if arg.startswith(f"--{name}="):
            return arg.split("=", 1)[1]
        if arg == f"--{name}":
            return command[i + 1]
    return None


def _values(command: list[str], name: str) -> list[str]:
    """The items of the list option `--name=[a,b]`."""
    value = _flag(command, name)
    return value.strip("[]").split(",") if value.strip("[]") else []


def test_the_stages_chain_each_from_the_previous_checkpoint(tmp_path):
    cfg = RecipeConfig(output_dir=str(tmp_path / "r"), dagger=DaggerSettings(rounds=2, stop_radius_m=7.5))
    steps = recipe_steps(cfg)
    assert [s.name for s in steps] == [
        "dataset", "grounding-data", "grounding", "navigation", "dagger-r1-rollouts", "dagger-r1-train",
        "dagger-r2-rollouts", "dagger-r2-train", "eval",
    ]  # fmt: skip
    by_name = {s.name: s for s in steps}
    out = tmp_path / "r"
    assert _flag(by_name["grounding"].command, "stage") == "grounding"
    assert _flag(by_name["navigation"].command, "init.checkpoint") == str(out / "grounding")
    assert _flag(by_name["navigation"].command, "init.matching") == "true"
    assert _flag(by_name["dagger-r1-rollouts"].command, "checkpoint") == str(out / "navigation")
    assert _flag(by_name["dagger-r2-rollouts"].command, "checkpoint") == str(out / "dagger" / "r1" / "train")
    assert _flag(by_name["dagger-r1-rollouts"].command, "stop_radius_m") == "7.5"
    r1, r2 = out / "dagger" / "r1" / "data", out / "dagger" / "r2" / "data"
    assert _flag(by_name["dagger-r1-train"].command, "data.extra_train_roots") == f"[{r1}]"
    assert _flag(by_name["dagger-r2-train"].command, "data.extra_train_roots") == f"[{r1},{r2}]"
    assert _flag(by_name["eval"].command, "checkpoint") == str(out / "dagger" / "r2" / "train")
    assert (
        "box_servo" in _values(by_name["eval"].command, "baselines")
        and _flag(by_name["eval"].command, "max_episodes") is None
    )
    assert _flag(by_name["grounding"].command, "steps") == str(cfg.grounding.steps)
    assert _flag(by_name["dagger-r2-train"].command, "time_limit_minutes") == str(cfg.dagger.train.minutes)
    assert {_flag(s.command, "optim.horizon") for s in steps if s.kind == KIND_TRAIN} == {"steps"}


def test_the_recipe_seed_reaches_every_training_stage_and_defaults_to_train_pys(tmp_path):
    seeded = RecipeConfig(output_dir=str(tmp_path / "r"), seed=11, dagger=DaggerSettings(rounds=1))
    train_steps = [s for s in recipe_steps(seeded) if s.kind == KIND_TRAIN]
    assert [s.name for s in train_steps] == ["grounding", "navigation", "dagger-r1-train"]
    assert {_flag(s.command, "seed") for s in train_steps} == {"11"}
    # the default is train.py's own seed (7), so a recipe run without --seed trains what it trained before
    default = RecipeConfig(output_dir=str(tmp_path / "d"))
    assert {_flag(s.command, "seed") for s in recipe_steps(default) if s.kind == KIND_TRAIN} == {"7"}
    # the DAgger rollouts keep their per-round seed whatever the training seed
    rollouts = next(s for s in recipe_steps(seeded) if s.name == "dagger-r1-rollouts")
    assert _flag(rollouts.command, "seed") == "1"


def test_extra_datasets_are_generated_and_join_navigation_and_dagger_training(tmp_path):
    cfg = RecipeConfig(
        output_dir=str(tmp_path),
        extra_toolchain_configs=["configs/toolchain/embedded-small-extra.yaml"],
        dagger=DaggerSettings(rounds=1),
    )
    by_name = {s.name: s for s in recipe_steps(cfg)}
    extra = "outputs/datasets/embedded-small-extra"  # the output_dir of that toolchain YAML
    generate = by_name["dataset-extra1"].command
    assert generate[-1] == f"--output_dir={extra}" and generate[-2].endswith("embedded-small-extra.yaml")
    assert _flag(by_name["navigation"].command, "data.extra_train_roots") == f"[{extra}]"
    r1 = tmp_path / "dagger" / "r1" / "data"
    assert _flag(by_name["dagger-r1-train"].command, "data.extra_train_roots") == f"[{extra},{r1}]"
    assert _flag(by_name["grounding"].command, "data.extra_train_roots") is None
    assert _flag(by_name["dagger-r1-rollouts"].command, "source_root") == cfg.dataset_root


def test_the_extra_routes_join_the_grounding_stage_when_asked(tmp_path):
    extra = "configs/toolchain/embedded-small-extra.yaml"
    cfg = RecipeConfig(output_dir=str(tmp_path), extra_toolchain_configs=[extra], grounding_extra_routes=True)
    by_name = {s.name: s for s in recipe_steps(cfg)}
    root = "outputs/datasets/embedded-small-extra"
    assert _flag(by_name["grounding"].command, "data.extra_train_roots") == f"[{root}]"
    assert _flag(by_name["navigation"].command, "data.extra_train_roots") == f"[{root}]"
    without_extra = RecipeConfig(output_dir=str(tmp_path), grounding_extra_routes=True)
    grounding = next(s for s in recipe_steps(without_extra) if s.name == "grounding")
    assert _flag(grounding.command, "data.extra_train_roots") is None


def test_without_grounding_pretraining_or_dagger_the_navigation_stage_is_evaluated(tmp_path):
    cfg = RecipeConfig(
        output_dir=str(tmp_path), grounding=StageBudget(steps=0), dagger=DaggerSettings(rounds=0)
    )
    steps = recipe_steps(cfg)
    assert [s.name for s in steps] == ["dataset", "navigation", "eval"]
    assert _flag(steps[1].command, "init.checkpoint") is None
    assert _flag(steps[2].command, "checkpoint") == str(tmp_path / "navigation")


def test_a_shared_grounding_stage_replaces_this_recipes_own(tmp_path, monkeypatch):
    shared = tmp_path / "recipe" / "grounding"
    cfg = RecipeConfig(output_dir=str(tmp_path / "arm"), grounding_from=str(shared))
    steps = recipe_steps(cfg)
    assert [s.name for s in steps] == [
        "dataset",
        "navigation",
        "dagger-r1-rollouts",
        "dagger-r1-train",
        "eval",
    ]
    assert _flag(steps[1].command, "init.checkpoint") == str(shared)
    assert _flag(steps[1].command, "init.matching") == "true"
    ran = []

    class _Finished:
        def wait(self) -> int:
            return 0

    def record(command, env):
        ran.append(command)
        return _Finished()

    monkeypatch.setattr(recipe_run, "start_group", record)
    with pytest.raises(RuntimeError, match="no training run there"):  # before any step runs
        run_recipe(cfg)
    assert ran == [] and not (tmp_path / "arm").exists()
    (shared / "checkpoints").mkdir(parents=True)
    (shared / "checkpoints" / "last").write_text("step-000010\n")
    run_recipe(cfg)
    assert len(ran) == len(steps) and _flag(ran[1], "init.checkpoint") == str(shared)
    with pytest.raises(ValueError, match="grounding.steps=0"):
        RecipeConfig(grounding_from=str(shared), grounding=StageBudget(steps=0))


def test_more_cities_are_generated_with_the_datasets_and_their_unseen_split_evaluated(tmp_path):
    more = "configs/toolchain/embedded-small-unseen-more.yaml"
    cfg = RecipeConfig(
        output_dir=str(tmp_path), dagger=DaggerSettings(rounds=0), eval=EvalSettings(more_cities=[more])
    )
    steps = recipe_steps(cfg)
    assert [s.name for s in steps] == [
        "dataset", "dataset-embedded-small-unseen-more", "grounding-data", "grounding", "navigation", "eval",
        "eval-embedded-small-unseen-more",
    ]  # fmt: skip
    by_name = {s.name: s for s in steps}
    root = "outputs/datasets/embedded-small-unseen-more"  # the output_dir of that toolchain YAML
    generate = by_name["dataset-embedded-small-unseen-more"].command
    assert generate[-1] == f"--output_dir={root}" and generate[-2].endswith(more.split("/")[-1])
    evaluate, main = by_name["eval-embedded-small-unseen-more"], by_name["eval"]
    assert evaluate.kind == KIND_EVAL and evaluate.folder == tmp_path / "eval-embedded-small-unseen-more"
    assert (
        _flag(evaluate.command, "dataset_root") == root
        and _flag(evaluate.command, "split") == "[test_unseen]"
    )
    assert (
        _flag(evaluate.command, "checkpoint")
        == _flag(main.command, "checkpoint")
        == str(tmp_path / "navigation")
    )
    assert _values(evaluate.command, "baselines") == _values(main.command, "baselines") == cfg.eval.baselines
    assert _flag(main.command, "dataset_root") == cfg.dataset_root  # the main splits stay embedded-small's


def test_a_dagger_setting_the_round_rejects_fails_when_the_recipe_is_configured():
    with pytest.raises(ValueError, match="stop_radius_m"):
        DaggerSettings(stop_radius_m=25.0)


def test_the_shipped_recipes_and_ablations_parse():
    configs = sorted((REPO_ROOT / "configs" / "recipe").rglob("*.yaml"))
    assert len(configs) >= 9  # main job, recipe, 7 ablations
    for path in configs:
        cfg = load_yaml_config(RecipeConfig, path, [])
        assert cfg.navigation.steps > 0 and cfg.eval.max_episodes == 0, path  # full test splits
        assert resolve_config_path(cfg.train_config).is_file(), path
        assert all(resolve_config_path(c).is_file() for c in cfg.extra_toolchain_configs), path
        assert all(resolve_config_path(c).is_file() for c in cfg.eval.more_cities), path


def _script(tmp_path, name: str, kind: str, code: str) -> RecipeStep:
    return RecipeStep(name, kind, [sys.executable, "-c", code], tmp_path / name)


def test_runner_skips_complete_steps_resumes_training_and_reevaluates_new_weights(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    record = f"import sys; open({str(log)!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')"
    steps = [
        _script(tmp_path, "data", KIND_DATA, record),
        _script(tmp_path, "train", KIND_TRAIN, record),
        _script(tmp_path, "eval", KIND_EVAL, record),
    ]
    monkeypatch.setattr(recipe_run, "recipe_steps", lambda cfg: steps)
    (tmp_path / "train" / "checkpoints").mkdir(parents=True)
    (tmp_path / "train" / "checkpoints" / "last").write_text("step-000002\n")  # an interrupted run
    state = run_recipe(RecipeConfig(output_dir=str(tmp_path / "out")))
    assert log.read_text().splitlines() == ["", "--resume=true", "--overwrite=true"]
    assert all((tmp_path / name / DONE_MARKER).is_file() for name in ("data", "train", "eval"))
    assert set(state["steps"]) == {"data", "train", "eval"}
    (tmp_path / "eval" / DONE_MARKER).unlink()
    run_recipe(RecipeConfig(output_dir=str(tmp_path / "out")))  # only eval runs, on unchanged weights
    assert log.read_text().splitlines()[3:] == ["--overwrite=false"]


def test_a_failing_step_stops_the_recipe_and_is_not_marked(tmp_path, monkeypatch):
    steps = [
        _script(tmp_path, "bad", KIND_DATA, "raise SystemExit(3)"),
        _script(tmp_path, "next", KIND_DATA, ""),
    ]
    monkeypatch.setattr(recipe_run, "recipe_steps", lambda cfg: steps)
    with pytest.raises(RuntimeError, match="recipe step bad failed with exit code 3"):
        run_recipe(RecipeConfig(output_dir=str(tmp_path / "out")))
    assert not (tmp_path / "bad" / DONE_MARKER).exists() and not (tmp_path / "next").exists()
    assert recipe_main([f"--output_dir={tmp_path / 'out'}"]) == 1


def test_command_line_errors_and_help(capsys):
    assert recipe_main(["--navigation.stepz=3"]) == 2
    assert "navigation.steps" in capsys.readouterr().err
    assert recipe_main(["--navigation.steps=0"]) == 2
    assert recipe_main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "--dagger.rounds INT" in text and "(default: 1500)" in text and "examples:" in text


def test_the_long_route_arms_differ_in_the_memory_only_and_evaluate_long_episodes():
    from openfly_agent.training.config import TrainConfig

    arms = ["current_frame", "uniform_history", "random_keyframes", "keyframes", "uniform_history_merging",
            "keyframes_merging"]  # fmt: skip
    base = load_yaml_config(RecipeConfig, REPO_ROOT / "configs" / "recipe" / "long-recipe.yaml", [])
    memory = []
    for arm in arms:
        cfg = load_yaml_config(
            RecipeConfig, REPO_ROOT / "configs" / "recipe" / "long-ablations" / f"{arm}.yaml", []
        )
        assert (cfg.toolchain_config, cfg.dataset_root) == (
            "configs/toolchain/embedded-long.yaml",
            "outputs/datasets/embedded-long",
        )
        assert (cfg.grounding, cfg.navigation, cfg.seed, cfg.eval) == (
            base.grounding,
            base.navigation,
            base.seed,
            base.eval,
        )
        train = load_yaml_config(TrainConfig, resolve_config_path(cfg.train_config), [])
        memory.append((train.model.memory.capacity > 0, train.data.history.mode, train.model.merging.enabled))
        evaluation = next(s for s in recipe_steps(cfg) if s.name == "eval")
        assert _flag(evaluation.command, "max_steps") == "200"
    assert memory == [
        (False, "none", False),
        (True, "uniform", False),
        (True, "random", False),
        (True, "keyframes", False),
        (True, "uniform", True),
        (True, "keyframes", True),
    ]
    assert base.extra_toolchain_configs == [] and base.eval.more_cities == []
    main = next(s for s in recipe_steps(RecipeConfig()) if s.name == "eval")
    assert _flag(main.command, "max_steps") is None  # the default cap is eval.py's own


def test_sigterm_stops_the_running_stage_with_the_recipe(tmp_path, monkeypatch, capsys):
    """A scheduler's SIGTERM to `python -m openfly_agent.recipe` reaches its running stage: the stage's process
    is stopped and reaped (not left running as an orphan), and the command says how to resume, exit code 143."""
    started = []

    def stage_that_runs_on(command, env):
        proc = start_group([sys.executable, "-c", "import time; time.sleep(300)"], env=env)
        started.append(proc)
        wait = proc.wait

        def wait_once_signalled(*args, **kwargs):  # the recipe waits on its stage: SIGTERM arrives then
            if not getattr(wait_once_signalled, "sent", False):
                wait_once_signalled.sent = True
                os.kill(os.getpid(), signal.SIGTERM)
            return wait(*args, **kwargs)

        proc.wait = wait_once_signalled
        return proc

    monkeypatch.setattr(recipe_run, "start_group", stage_that_runs_on)
    before = signal.getsignal(signal.SIGTERM)
    assert recipe_main([f"--output_dir={tmp_path / 'r'}"]) == EXIT_TERMINATED
    assert len(started) == 1 and started[0].poll() is not None  # stopped and reaped, not running on
    assert started[0].returncode == -signal.SIGTERM
    assert (
        "terminated (SIGTERM), its stage stopped; run the same command again to resume"
        in capsys.readouterr().err
    )
    assert signal.getsignal(signal.SIGTERM) == before  # the handler is the recipe's only while it runs

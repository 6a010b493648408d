"""The recipe's RL stage: off in every shipped recipe but tiny-recipe-rl.yaml; when on, train.py --stage=rl from
the navigation stage or the last DAgger round, in one process, resumed and guarded like the other stages, then
the evaluation of its agent and, on the same episodes, of the agent it started from, paired in the report."""

from __future__ import annotations

import pytest
from eval_helpers import policy_folder

from openfly_agent.eval.compare import PairingError
from openfly_agent.recipe import DaggerSettings, RecipeConfig, StageBudget, recipe_steps, run_recipe
from openfly_agent.recipe import run as recipe_run
from openfly_agent.recipe.__main__ import main as recipe_main
from openfly_agent.recipe.config import stage_train_config
from openfly_agent.recipe.progress import recipe_report, stage_progress
from openfly_agent.recipe.report import rl_comparison
from openfly_agent.recipe.run import DONE_MARKER, KIND_EVAL, KIND_TRAIN
from openfly_agent.training.state import TrainerState
from openfly_agent.utils.config import REPO_ROOT, load_yaml_config

RECIPES = REPO_ROOT / "configs" / "recipe"
RL_RECIPE = "tiny-recipe-rl.yaml"


def _flag(command: list[str], name: str) -> str | None:
    values = [a.split("=", 1)[1] for a in command if a.startswith(f"--{name}=")]
    assert len(values) <= 1, (name, command)
    return values[0] if values else None


def _rl_recipe(tmp_path, rounds: int = 0, **settings) -> RecipeConfig:
    rl = StageBudget(steps=5, minutes=7.0, overrides={"rl": {"group_size": 8}, "optim": {"lr": 1.0e-5}})
    return RecipeConfig(
        output_dir=str(tmp_path / "r"), dagger=DaggerSettings(rounds=rounds), rl=rl, **settings
    )


@pytest.mark.parametrize(
    "name", sorted(p.relative_to(RECIPES).as_posix() for p in RECIPES.rglob("*.yaml") if p.name != RL_RECIPE)
)
def test_no_other_shipped_recipe_has_an_rl_stage(name):
    cfg = load_yaml_config(RecipeConfig, RECIPES / name, [])
    assert cfg.rl.steps == 0
    names = [s.name for s in recipe_steps(cfg)]
    assert "rl" not in names and "eval-before-rl" not in names
    assert RecipeConfig().rl.steps == 0  # off by default


def test_the_rl_stage_starts_from_the_navigation_stage_in_one_process(tmp_path):
    cfg = _rl_recipe(tmp_path, processes=2, torch_threads=3)
    steps = recipe_steps(cfg)
    assert [s.name for s in steps] == [
        "dataset", "grounding-data", "grounding", "navigation", "rl", "eval", "eval-before-rl",
    ]  # fmt: skip
    by_name, out = {s.name: s for s in steps}, tmp_path / "r"
    rl = by_name["rl"]
    assert rl.kind == KIND_TRAIN and rl.folder == out / "rl" and rl.steps == 5
    assert rl.command[1].endswith("train.py")  # no accelerate launcher: the RL stage runs in one process
    assert rl.env == {"OMP_NUM_THREADS": "3"}
    assert by_name["navigation"].command[1:3] == [
        "-m",
        "accelerate.commands.launch",
    ]  # the others keep theirs
    assert _flag(rl.command, "stage") == "rl"
    assert _flag(rl.command, "init.checkpoint") == str(out / "navigation")
    assert (_flag(rl.command, "steps"), _flag(rl.command, "time_limit_minutes")) == ("5", "7.0")
    assert (_flag(rl.command, "rl.group_size"), _flag(rl.command, "optim.lr")) == ("8", "1e-05")
    evaluation, before = by_name["eval"], by_name["eval-before-rl"]
    assert _flag(evaluation.command, "checkpoint") == str(out / "rl")
    assert before.kind == KIND_EVAL and before.folder == out / "eval_before_rl"
    assert _flag(before.command, "checkpoint") == str(out / "navigation")
    assert _flag(before.command, "baselines") == "[]"  # the agent alone: the baselines are in eval/
    # the same episodes: every other option of the two evaluations is the same
    same = ("split", "dataset_root", "max_episodes", "max_steps", "batch_size", "torch_threads", "sim.type")
    assert all(_flag(before.command, f) == _flag(evaluation.command, f) for f in same)


def test_the_agent_before_rl_flies_the_more_cities_too(tmp_path):
    cities = RECIPES.parent / "toolchain" / "embedded-small-unseen-more.yaml"
    cfg = _rl_recipe(tmp_path)
    cfg.eval.more_cities = [str(cities)]
    steps = recipe_steps(cfg)
    by_name, out = {s.name: s for s in steps}, tmp_path / "r"
    names = [s.name for s in steps]
    assert names[-4:] == [
        "eval", "eval-before-rl", "eval-embedded-small-unseen-more", "eval-before-rl-embedded-small-unseen-more",
    ]  # fmt: skip
    after, before = by_name[names[-2]], by_name[names[-1]]
    assert before.kind == KIND_EVAL and before.folder == out / "eval_before_rl-embedded-small-unseen-more"
    assert _flag(before.command, "checkpoint") == str(out / "navigation")
    assert _flag(after.command, "checkpoint") == str(out / "rl")
    assert _flag(before.command, "baselines") == "[]"
    same = ("split", "dataset_root", "max_episodes", "max_steps", "batch_size", "torch_threads", "sim.type")
    assert all(_flag(before.command, f) == _flag(after.command, f) for f in same)
    assert _flag(before.command, "split") == "[test_unseen]"
    # without an RL stage there is no agent before it to fly
    cfg.rl = StageBudget(steps=0)
    assert not [s for s in recipe_steps(cfg) if s.name.startswith("eval-before-rl")]


def test_after_dagger_rounds_the_rl_stage_starts_from_the_last_round(tmp_path):
    cfg = _rl_recipe(tmp_path, rounds=2)
    by_name = {s.name: s for s in recipe_steps(cfg)}
    last_round = tmp_path / "r" / "dagger" / "r2" / "train"
    assert list(by_name)[-4:] == ["dagger-r2-train", "rl", "eval", "eval-before-rl"]
    assert _flag(by_name["rl"].command, "init.checkpoint") == str(last_round)
    assert _flag(by_name["eval-before-rl"].command, "checkpoint") == str(last_round)


def test_the_shipped_rl_recipe_is_the_tiny_recipe_plus_the_rl_stage():
    tiny = load_yaml_config(RecipeConfig, RECIPES / "tiny-recipe.yaml", [])
    cfg = load_yaml_config(RecipeConfig, RECIPES / RL_RECIPE, [])
    assert cfg.rl.steps == 50
    resolved = stage_train_config(cfg, cfg.rl, "rl")
    # the main job's arm "temperature 0.5" (docs/experiments/2026-11-28-rl-stage-on-the-main-job.md)
    assert (resolved.rl.group_size, resolved.rl.episodes_per_update, resolved.rl.temperature) == (4, 8, 0.5)
    assert (resolved.optim.lr, resolved.optim.schedule) == (1.0e-4, "constant")
    assert resolved.optim.warmup_steps == 0  # the schedule steps once per update: no 50-update warmup
    # its decision reads val; the evaluation is otherwise the tiny recipe's (the more cities included)
    assert cfg.eval.splits == ["val", *tiny.eval.splits] and cfg.eval.more_cities == tiny.eval.more_cities
    # every step before the RL stage is the tiny recipe's, up to the output folder
    ours, theirs = recipe_steps(cfg), recipe_steps(tiny)
    first = [s.name for s in ours].index("rl")
    assert [s.name for s in theirs][:first] == [s.name for s in ours][:first]
    for mine, its in zip(ours[:first], theirs[:first]):
        assert mine.command == [a.replace("outputs/recipe/", "outputs/recipe-rl/") for a in its.command]


def test_a_bad_rl_setting_is_one_line_before_anything_runs(monkeypatch, capsys):
    def no_command(*_args, **_kwargs):
        raise AssertionError("a stage command ran")

    monkeypatch.setattr(recipe_run, "start_group", no_command)
    args = ["--config_path", str(RECIPES / RL_RECIPE), "--rl.overrides={rl: {group_size: 1}}"]
    assert recipe_main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "rl.overrides: train.py: rl.group_size must be >= 2" in err, err


class _Finished:
    def wait(self) -> int:
        return 0


def test_an_interrupted_rl_stage_resumes_and_its_guard_is_reported(tmp_path, monkeypatch):
    cfg = _rl_recipe(tmp_path, grounding=StageBudget(steps=0))
    out = tmp_path / "r"
    for name in ("dataset", "navigation"):  # finished before the interruption
        (out / name).mkdir(parents=True)
        (out / name / DONE_MARKER).write_text("{}\n")
    checkpoint = out / "rl" / "checkpoints" / "step-000003"  # the RL stage stopped after its update 3
    checkpoint.mkdir(parents=True)
    TrainerState(step=3).save(checkpoint)
    (out / "rl" / "checkpoints" / "last").write_text("step-000003\n")
    ran = []
    monkeypatch.setattr(recipe_run, "start_group", lambda command, env: ran.append(command) or _Finished())
    run_recipe(cfg)
    assert [c[1].rsplit("/", 1)[-1] for c in ran] == ["train.py", "eval.py", "eval.py"]
    assert ran[0][-1] == "--resume=true"
    assert ran[1][-1] == ran[2][-1] == "--overwrite=true"  # new weights: both evaluations start over
    # the progress header counts the stage's updates against its steps, with its own guard
    progress = {p.name: p for p in stage_progress(cfg)}
    assert (progress["rl"].steps_done, progress["rl"].steps_planned, progress["rl"].minutes) == (3, 5, 7.0)
    assert "rl: 3 of 5 steps (its 7-minute guard stopped it)" in progress["rl"].describe()


def test_the_report_pairs_the_rl_agent_with_the_agent_it_started_from(tmp_path):
    cfg = _rl_recipe(tmp_path)
    out = tmp_path / "r"
    # test_seen: before RL e0 and e1 succeed, after RL e0, e2 and e3 (both 1, only before 1, only after 2)
    policy_folder(out / "eval_before_rl", {"e0": True, "e1": True, "e2": False, "e3": False})
    policy_folder(out / "eval", {"e0": True, "e1": False, "e2": True, "e3": True}, checkpoint="rl")
    assert rl_comparison(out) is None and "## rl" not in recipe_report(cfg)  # not the recipe's (no marker)
    for folder in ("eval", "eval_before_rl"):
        (out / folder / DONE_MARKER).write_text("{}\n")
    seen = rl_comparison(out)["splits"]["test_seen"]["standard"]
    assert (seen["sr_a_pct"], seen["sr_b_pct"], seen["sr_diff_pp"]) == (50.0, 75.0, 25.0)
    # Newcombe's method 10 for this table, worked by hand in tests/eval/test_eval_compare.py
    assert seen["sr_diff_ci_pp"] == pytest.approx([-46.1326, 74.6849], abs=1e-3)
    report = recipe_report(cfg)
    section = report[report.index("## rl") :]
    assert (
        "A is agent_before_rl (the agent the RL stage started from), B is agent (the RL stage's)" in section
    )
    assert (
        f"- A: {out / 'eval_before_rl' / 'agent'}" in section and f"- B: {out / 'eval' / 'agent'}" in section
    )
    assert (
        "| test_seen / `standard` | 4 | 50.0 / 75.0 | +25.0 [-46.1, +74.7] | 1.000 | 1 / 1 / 2 / 0 |"
        in section
    )
    # the recipe without an RL stage reports no pairing, even with such folders around
    assert "## rl" not in recipe_report(RecipeConfig(output_dir=str(out)))


def test_the_report_pairs_the_more_cities_and_pools_every_unseen_episode(tmp_path):
    cfg = _rl_recipe(tmp_path)
    out = tmp_path / "r"
    unseen = "test_unseen"
    # test_unseen: before RL u0 succeeds, after RL u0 and u1
    policy_folder(out / "eval_before_rl", {"u0": True, "u1": False}, split=unseen)
    policy_folder(out / "eval", {"u0": True, "u1": True}, split=unseen, checkpoint="rl")
    # the more cities: before RL c0 and c1, after RL c1 and c2
    policy_folder(out / "eval_before_rl-more", {"c0": True, "c1": True, "c2": False}, split=unseen)
    policy_folder(out / "eval-more", {"c0": False, "c1": True, "c2": True}, split=unseen, checkpoint="rl")
    for folder in ("eval", "eval_before_rl", "eval-more"):
        (out / folder / DONE_MARKER).write_text("{}\n")
    assert list(rl_comparison(out)["splits"]) == [unseen]  # the city's agent before RL is not finished
    (out / "eval_before_rl-more" / DONE_MARKER).write_text("{}\n")
    splits = rl_comparison(out)["splits"]
    assert list(splits) == [unseen, "test_unseen (more)", "all unseen"]
    city, pooled = splits["test_unseen (more)"]["standard"], splits["all unseen"]["standard"]
    assert city["counts"] == {"both": 1, "only_a": 1, "only_b": 1, "neither": 0}
    assert (city["episodes"], city["sr_a_pct"], city["sr_b_pct"], city["sr_diff_pp"]) == (
        3,
        200 / 3,
        200 / 3,
        0.0,
    )
    # pooled: A succeeds on u0, c0, c1 (3 of 5), B on u0, u1, c1, c2 (4 of 5)
    assert pooled["counts"] == {"both": 2, "only_a": 1, "only_b": 2, "neither": 0}
    assert (pooled["episodes"], pooled["sr_a_pct"], pooled["sr_b_pct"]) == (5, 60.0, 80.0)
    assert pooled["sr_diff_pp"] == pytest.approx(20.0)
    assert pooled["mcnemar_p"] == pytest.approx(1.0)  # 1 against 2 discordant: 2 x (1 + 3) / 8
    section = recipe_report(cfg)[recipe_report(cfg).index("## rl") :]
    assert "`all unseen` pools them with test_unseen" in section
    assert "| all unseen / `standard` | 5 | 60.0 / 80.0 | +20.0 [" in section


def test_a_city_flown_on_other_episodes_before_rl_is_refused(tmp_path):
    out = tmp_path / "r"
    policy_folder(out / "eval_before_rl", {"u0": True}, split="test_unseen")
    policy_folder(out / "eval", {"u0": True}, split="test_unseen", checkpoint="rl")
    policy_folder(out / "eval_before_rl-more", {"c0": True}, split="test_unseen")
    policy_folder(out / "eval-more", {"c9": True}, split="test_unseen", checkpoint="rl")
    for folder in ("eval", "eval_before_rl", "eval-more", "eval_before_rl-more"):
        (out / folder / DONE_MARKER).write_text("{}\n")
    with pytest.raises(PairingError, match="flew other episodes"):
        rl_comparison(out)

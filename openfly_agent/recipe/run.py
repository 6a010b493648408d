"""Run the recipe's stages in order as child processes, skipping those already complete.

Each stage is the project's own command (the toolchain, `train.py` under accelerate, `eval.py`), so the recipe
is exactly what a user could type, and each of them resumes on its own: an interrupted stage continues where it
stopped on the next run. A stage is complete when its marker file exists (written after the command exits 0);
`recipe_state.json` records every stage's command and wall time.

    grounding data -> grounding stage -> navigation stage (init: grounding, matching tensors)
        -> DAgger round k: rollouts of the latest agent + training on all data (init: the latest agent)
        -> the RL stage when it has steps (init: the latest agent)
        -> closed-loop evaluation of the final agent with every baseline
        -> with the RL stage: the agent it started from on the same episodes (eval_before_rl/)
        -> the same on the test_unseen split of each of `eval.more_cities` (generated with the datasets), and
           with the RL stage the agent it started from there too (eval_before_rl-<cities>/)
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.recipe.config import RecipeConfig, StageBudget
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.utils.config import REPO_ROOT, load_yaml_config, resolve_config_path
from openfly_agent.utils.processes import start_group, stop_group

logger = logging.getLogger(__name__)

DONE_MARKER = ".recipe_done"
STATE_FILE = "recipe_state.json"
KIND_DATA, KIND_TRAIN, KIND_EVAL = "data", "train", "eval"
RL_DIR = "rl"  # the RL stage's training run
# the agent the RL stage started from, evaluated on the main evaluation's episodes (its policy folder: agent/),
# and on each more cities' as `eval_before_rl-<cities>`; not `eval-*`, the RL agent's folders of the more cities
EVAL_BEFORE_RL_DIR = "eval_before_rl"


def step_finished(folder: Path) -> bool:
    """Whether the recipe finished the step that writes `folder` (its completion marker is there)."""
    return (Path(folder) / DONE_MARKER).is_file()


@dataclass
class RecipeStep:
    """One command of the recipe.

    Attributes:
        name: the stage's name in logs and in recipe_state.json ("navigation", "dagger-r1-train", ...).
        kind: data | train | eval.
        command: the argument list (resume flags are added when the step runs).
        folder: where it writes; its marker `folder/.recipe_done` says the step is complete.
        env: environment variables it needs (thread counts).
        steps: a training step's budget of optimizer steps (0 for data and eval steps).
    """

    name: str
    kind: str
    command: list[str]
    folder: Path
    env: dict[str, str] = field(default_factory=dict)
    steps: int = 0

    @property
    def done(self) -> bool:
        return step_finished(self.folder)


def _train_launcher(cfg: RecipeConfig, processes: int) -> tuple[list[str], dict[str, str]]:
    """accelerate with `processes` one-thread processes (gloo), or one process of `torch_threads` threads."""
    if processes > 1:
        accelerate_config = str(resolve_config_path("configs/accelerate/cpu_2proc.yaml"))
        launch = [sys.executable, "-m", "accelerate.commands.launch", "--config_file", accelerate_config]
        return launch + ["--num_processes", str(processes)], {"OMP_NUM_THREADS": "1"}
    return [sys.executable], {"OMP_NUM_THREADS": str(cfg.torch_threads)}


def _train_step(
    cfg: RecipeConfig,
    name: str,
    folder: Path,
    budget: StageBudget,
    args: list[str],
    processes: int | None = None,
) -> RecipeStep:
    """train.py on the recipe's data with the stage's budget and settings; `processes`: the recipe's unless given
    (the RL stage runs in one)."""
    launcher, env = _train_launcher(cfg, cfg.processes if processes is None else processes)
    command = launcher + [
        str(REPO_ROOT / "train.py"),
        "--config_path", str(resolve_config_path(cfg.train_config)),
        f"--data.root={cfg.dataset_root}",
        f"--output_dir={folder}",
        f"--steps={budget.steps}",
        f"--time_limit_minutes={budget.minutes}",
        f"--optim.horizon={cfg.lr_horizon}",
        f"--seed={cfg.seed}",
        *args,
        *cfg.stage_flags(budget),
    ]  # fmt: skip
    return RecipeStep(name, KIND_TRAIN, command, folder, env, steps=budget.steps)


def recipe_steps(cfg: RecipeConfig) -> list[RecipeStep]:
    """The recipe's commands in order (nothing is run)."""
    out = Path(cfg.output_dir)
    toolchain = [sys.executable, "-m", "openfly_agent.toolchain"]
    steps = [
        RecipeStep(
            "dataset",
            KIND_DATA,
            toolchain + ["generate", "--config_path", str(resolve_config_path(cfg.toolchain_config)),
                         f"--output_dir={cfg.dataset_root}"],
            out / "dataset",
        ),
    ]  # fmt: skip
    extra_roots = []
    for k, config in enumerate(cfg.extra_toolchain_configs, 1):
        step, root = _generate_step(config, f"dataset-extra{k}", out)
        steps.append(step)
        extra_roots.append(root)
    more_cities = []  # (config name, dataset root) of the evaluation's more unseen cities, generated up front
    for config in cfg.eval.more_cities:
        name = resolve_config_path(config).stem
        step, root = _generate_step(config, f"dataset-{name}", out)
        steps.append(step)
        more_cities.append((name, root))
    init: list[str] = []
    if cfg.grounding_from:  # a shared grounding stage: no grounding data or training here
        init = [f"--init.checkpoint={cfg.grounding_from}", "--init.matching=true"]
    elif cfg.grounding.steps:
        steps.append(
            RecipeStep(
                "grounding-data",
                KIND_DATA,
                toolchain
                + ["grounding", f"--source_root={cfg.dataset_root}", f"--output_dir={cfg.grounding_root}"],
                out / "grounding-data",
            )
        )
        grounding_args = ["--stage=grounding", f"--data.grounding_root={cfg.grounding_root}"]
        if cfg.grounding_extra_routes and extra_roots:
            grounding_args.append(_extra_roots_flag(extra_roots))
        steps.append(_train_step(cfg, "grounding", out / "grounding", cfg.grounding, grounding_args))
        init = [f"--init.checkpoint={out / 'grounding'}", "--init.matching=true"]
    navigation_args = init + ([_extra_roots_flag(extra_roots)] if extra_roots else [])
    steps.append(_train_step(cfg, "navigation", out / "navigation", cfg.navigation, navigation_args))
    latest, extra_train = out / "navigation", list(extra_roots)
    for k in range(1, cfg.dagger.rounds + 1):
        round_dir = out / "dagger" / f"r{k}"
        extra_train.append(str(round_dir / "data"))
        d = cfg.dagger
        steps.append(
            RecipeStep(
                f"dagger-r{k}-rollouts",
                KIND_DATA,
                toolchain + [
                    "dagger-round", f"--checkpoint={latest}", f"--torch_threads={cfg.torch_threads}",
                    f"--source_root={cfg.dataset_root}", f"--output_dir={round_dir / 'data'}",
                    f"--round_name=r{k}", f"--episodes={d.episodes}", f"--max_policy_steps={d.max_policy_steps}",
                    f"--expert_mix={d.expert_mix}", f"--stop_radius_m={d.stop_radius_m}",
                    f"--num_envs={d.num_envs}", f"--seed={k}",
                ],
                round_dir / "data",
                {"OMP_NUM_THREADS": str(cfg.torch_threads)},
            )
        )  # fmt: skip
        round_args = [
            f"--init.checkpoint={latest}",
            "--init.matching=true",
            _extra_roots_flag(extra_train),
        ]
        steps.append(_train_step(cfg, f"dagger-r{k}-train", round_dir / "train", d.train, round_args))
        latest = round_dir / "train"
    before_rl = latest
    if cfg.rl.steps:
        steps.append(_rl_step(cfg, out, before_rl))
        latest = out / RL_DIR
    steps.append(_eval_step(cfg, "eval", latest, cfg.eval.splits, cfg.dataset_root, out / "eval"))
    if cfg.rl.steps:  # the agent the RL stage started from, alone (the baselines are in eval/), same episodes
        folder = out / EVAL_BEFORE_RL_DIR
        steps.append(
            _eval_step(cfg, "eval-before-rl", before_rl, cfg.eval.splits, cfg.dataset_root, folder, [])
        )
    for name, root in more_cities:
        steps.append(
            _eval_step(cfg, f"eval-{name}", latest, [C.SPLIT_TEST_UNSEEN], root, out / f"eval-{name}")
        )
        if cfg.rl.steps:  # ... and the agent the RL stage started from, on the same episodes
            folder = out / f"{EVAL_BEFORE_RL_DIR}-{name}"
            split = [C.SPLIT_TEST_UNSEEN]
            steps.append(_eval_step(cfg, f"eval-before-rl-{name}", before_rl, split, root, folder, []))
    return steps


def _rl_step(cfg: RecipeConfig, out: Path, start: Path) -> RecipeStep:
    """train.py --stage=rl from the agent trained in `start`, in one process (the stage runs in one)."""
    args = [f"--stage={C.STAGE_RL}", f"--init.checkpoint={start}"]
    return _train_step(cfg, "rl", out / RL_DIR, cfg.rl, args, processes=1)


def _generate_step(config: str, name: str, out: Path) -> tuple[RecipeStep, str]:
    """`toolchain generate` of a toolchain YAML into its own output_dir; returns the step and that root."""
    path = resolve_config_path(config)
    root = load_yaml_config(GenerateConfig, path, []).output_dir
    command = [sys.executable, "-m", "openfly_agent.toolchain", "generate", "--config_path", str(path)]
    return RecipeStep(name, KIND_DATA, command + [f"--output_dir={root}"], out / name), root


def _eval_step(
    cfg: RecipeConfig,
    name: str,
    checkpoint: Path,
    splits: list[str],
    dataset_root: str,
    folder: Path,
    baselines: list[str] | None = None,
) -> RecipeStep:
    """eval.py on the embedded simulator: the agent at `checkpoint` and `baselines` (None: eval.baselines) on
    `splits`."""
    e = cfg.eval
    baselines = e.baselines if baselines is None else baselines
    command = [
        sys.executable, str(REPO_ROOT / "eval.py"), f"--checkpoint={checkpoint}", "--sim.type=embedded",
        f"--split=[{','.join(splits)}]", f"--baselines=[{','.join(baselines)}]", f"--dataset_root={dataset_root}",
        f"--output_dir={folder}", f"--batch_size={e.batch_size}", f"--torch_threads={e.torch_threads}",
        *([f"--max_episodes={e.max_episodes}"] if e.max_episodes else []),
        *([f"--max_steps={e.max_steps}"] if e.max_steps != C.MAX_EPISODE_STEPS else []),
    ]  # fmt: skip
    return RecipeStep(name, KIND_EVAL, command, folder, {"OMP_NUM_THREADS": str(e.torch_threads)})


def _extra_roots_flag(roots: list) -> str:
    return "--data.extra_train_roots=[" + ",".join(str(r) for r in roots) + "]"


def _with_resume(step: RecipeStep, retrained: bool) -> list[str]:
    """The command as run now: training resumes an interrupted run; eval starts over after new training."""
    if step.kind == KIND_TRAIN:
        return step.command + [f"--resume={(step.folder / 'checkpoints' / 'last').exists()}".lower()]
    if step.kind == KIND_EVAL:
        return step.command + [f"--overwrite={str(retrained).lower()}"]
    return step.command


def _check_grounding_from(cfg: RecipeConfig) -> None:
    """A shared grounding stage must be a finished training run (its `checkpoints/last`), before anything runs."""
    if not cfg.grounding_from:
        return
    last = Path(cfg.grounding_from) / "checkpoints" / "last"
    if not last.exists():
        raise RuntimeError(
            f"grounding_from={cfg.grounding_from}: no training run there ({last} is missing); "
            "give the folder of a finished grounding stage, e.g. outputs/recipe/grounding"
        )


def run_recipe(cfg: RecipeConfig) -> dict:
    """Run every incomplete step of `cfg` in order; returns recipe_state.json's content.

    Raises:
        RuntimeError: a step exited non-zero (its name and exit code; its output went to the console), or
            `grounding_from` names no finished training run.
    """
    _check_grounding_from(cfg)
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / STATE_FILE
    state = json.loads(state_path.read_text()) if state_path.is_file() else {"steps": {}}
    state["config"] = asdict(cfg)
    retrained = False
    steps = recipe_steps(cfg)
    for index, step in enumerate(steps, 1):
        if step.done:
            logger.info(
                "[%d/%d] %s: complete (delete %s to run it again)", index, len(steps), step.name, step.folder
            )
            continue
        command = _with_resume(step, retrained)
        logger.info("[%d/%d] %s: %s", index, len(steps), step.name, " ".join(command))
        start = time.time()
        proc = start_group(command, env={**os.environ, **step.env})
        try:
            code = proc.wait()
        except (
            BaseException
        ):  # Ctrl-C / SIGTERM: the stage's processes stop too (training saves a checkpoint)
            stop_group(proc, grace_s=60.0)
            raise
        if code != 0:
            raise RuntimeError(f"recipe step {step.name} failed with exit code {code}: {' '.join(command)}")
        seconds = time.time() - start
        step.folder.mkdir(parents=True, exist_ok=True)
        (step.folder / DONE_MARKER).write_text(json.dumps({"seconds": round(seconds, 1)}) + "\n")
        retrained = retrained or step.kind == KIND_TRAIN
        state["steps"][step.name] = {"command": command, "seconds": round(seconds, 1)}
        state_path.write_text(json.dumps(state, indent=2) + "\n")
        logger.info("[%d/%d] %s: done in %.0f s", index, len(steps), step.name, seconds)
    return state

"""`RecipeConfig`: every stage of the navigation recipe and its budget (configs/recipe/*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import draccus

from openfly_agent import constants as C
from openfly_agent.toolchain.config import DaggerRoundConfig
from openfly_agent.training.config import HORIZONS, TrainConfig
from openfly_agent.utils.config import flat_settings, parse_config, resolve_config_path
from openfly_agent.utils.errors import root_cause


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


@dataclass
class StageBudget:
    """One training stage: it trains `steps` optimizer steps, so a run's result does not depend on the machine's
    speed; `minutes` is only a guard (a stage it stops is reported as cut short, openfly_agent/recipe/progress.py).
    steps 0 skips the stage."""

    steps: int = 1000  # optimizer steps (0: the stage is skipped)
    minutes: float = 10.0  # guard: wall-clock cap of the stage's training (train.py --time_limit_minutes)
    # train.py settings of this stage over the recipe's train_config and model, laid out as in a train config
    # (e.g. {optim: {lr: 1.0e-4}}); checked against TrainConfig when the recipe is loaded
    overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _check(self.steps >= 0, f"steps must be >= 0, got {self.steps}")
        _check(self.minutes > 0, f"minutes must be > 0, got {self.minutes}")


@dataclass
class DaggerSettings:
    """DAgger rounds: the latest agent flies train episodes, the A* expert labels every visited state, and the
    agent trains again on the original data plus every round's rollouts (toolchain/dagger_rounds.py)."""

    rounds: int = 1  # 0: no DAgger
    episodes: int = 300  # rollouts per round (train episodes drawn without replacement)
    max_policy_steps: int = 40  # agent-flown states per rollout at most; then the expert flies to the goal
    expert_mix: float = 0.0  # probability that the expert's action is flown instead of the agent's
    # the expert's STOP at every state within this distance of the goal (0: only within A*'s tolerance)
    stop_radius_m: float = DaggerRoundConfig.stop_radius_m
    num_envs: int = 16  # rollouts in lockstep (the agent's batch)
    train: StageBudget = field(default_factory=lambda: StageBudget(steps=300, minutes=5.0))

    def __post_init__(self) -> None:
        _check(self.rounds >= 0, f"dagger.rounds must be >= 0, got {self.rounds}")
        _check(self.episodes >= 1, f"dagger.episodes must be >= 1, got {self.episodes}")
        # the round's own checks now, not after the training stages before it
        DaggerRoundConfig(
            episodes=self.episodes,
            expert_mix=self.expert_mix,
            max_policy_steps=self.max_policy_steps,
            stop_radius_m=self.stop_radius_m,
            num_envs=self.num_envs,
        )


@dataclass
class EvalSettings:
    """The closed-loop evaluation at the end (eval.py on the embedded simulator)."""

    # the test splits, evaluated in full by default
    splits: list[str] = field(default_factory=lambda: [C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN])
    # evaluated next to the agent (box_servo: the reflex on the true target box, the perception bar;
    # agent_true_box: the same agent fed the true target box, so the gap to it is what its grounding costs)
    baselines: list[str] = field(
        default_factory=lambda: ["random", "stop", "forward", "oracle", "box_servo", "agent_true_box"]
    )
    max_episodes: int = 0  # per split, evenly spaced (0: the full splits)
    # actions per episode at most, STOP included (eval.py --max_steps); long routes need more than the default
    max_steps: int = C.MAX_EPISODE_STEPS
    # toolchain YAMLs of more unseen cities (e.g. configs/toolchain/embedded-small-unseen-more.yaml): each is
    # generated into its own output_dir and its test_unseen split evaluated with the same policies into
    # <output_dir>/eval-<config name>/, so the agent is also measured on cities no choice was made on
    more_cities: list[str] = field(default_factory=list)
    batch_size: int = 16  # episodes in lockstep
    torch_threads: int = 2  # torch threads of the evaluation process

    def __post_init__(self) -> None:
        _check(self.max_episodes >= 0, f"eval.max_episodes must be >= 0, got {self.max_episodes}")
        _check(self.max_steps >= 1, f"eval.max_steps must be >= 1, got {self.max_steps}")


@dataclass
class RecipeConfig:
    """`python -m openfly_agent.recipe`: the stages in order, each skipped when its output is complete.

    Relative paths: outputs are relative to the working directory, configs are read from it or else from the
    repository (as everywhere in the project).
    """

    # grounding/, navigation/, dagger/r<k>/, rl/, eval/, eval_before_rl/ and recipe_state.json
    output_dir: str = "outputs/recipe"
    dataset_root: str = "outputs/datasets/embedded-small"  # generated when missing
    toolchain_config: str = "configs/toolchain/embedded-small.yaml"  # how the dataset is generated
    grounding_root: str = "outputs/datasets/grounding-small"  # the referring-expression dataset (generated)
    # toolchain YAMLs of more navigation data, each generated into its own output_dir; their train splits join
    # the navigation stage and the DAgger rounds (the test splits stay dataset_root's)
    extra_toolchain_configs: list[str] = field(default_factory=list)
    # true: those train splits also join the grounding stage, as more navigation targets (the stage's
    # data.instruction_fraction of its samples are navigation steps seen as instruction -> target box)
    grounding_extra_routes: bool = False
    # a grounding stage trained before (a training run folder, e.g. another recipe run's grounding/): the
    # navigation stage starts from its last checkpoint and this recipe trains none, so ablation arms that change
    # only the navigation stage share one grounding stage (None: train the stage configured in `grounding`)
    grounding_from: str | None = None
    train_config: str = "configs/train/tiny.yaml"  # train.py preset every stage starts from
    # a model section file laid over train_config's model section in every stage (train.py --model=<file>), e.g.
    # configs/model/tiny-adopted.yaml, the adopted tiny model (null: train_config's model as it is)
    model: str | None = None
    processes: int = 2  # training processes of one torch thread each (1: one process with torch_threads)
    torch_threads: int = 2  # torch threads of one-process training and of the DAgger rollouts
    # train.py --optim.horizon of every stage: `steps` decays the lr over the stage's steps (the same schedule on
    # any machine); `time` over its minutes when they end first (how runs before issue 39 were budgeted)
    lr_horizon: str = "steps"
    # the training seed of every stage (train.py --seed: model init, data order and augmentation); run the
    # recipe with 3 seeds to see how far its table moves with training alone (docs/RESULTS.md, "The main job")
    seed: int = TrainConfig.seed
    grounding: StageBudget = field(default_factory=lambda: StageBudget(steps=1500, minutes=8.0))
    navigation: StageBudget = field(default_factory=lambda: StageBudget(steps=1500, minutes=10.0))
    dagger: DaggerSettings = field(default_factory=DaggerSettings)
    # the RL stage (train.py --stage=rl, docs/TRAINING.md "The RL stage") from the navigation stage or the last
    # DAgger round: `steps` updates, its `overrides` hold the `rl` and `optim` settings (e.g. {rl: {group_size:
    # 8}, optim: {lr: 1.0e-5}}); when it runs, the evaluation flies its agent and, on the same episodes, the agent
    # it started from, and the report gives their paired difference. 0 steps (the default): no RL stage
    rl: StageBudget = field(default_factory=lambda: StageBudget(steps=0, minutes=60.0))
    eval: EvalSettings = field(default_factory=EvalSettings)

    def __post_init__(self) -> None:
        _check(self.processes >= 1, f"processes must be >= 1, got {self.processes}")
        _check(self.torch_threads >= 1, f"torch_threads must be >= 1, got {self.torch_threads}")
        _check(self.lr_horizon in HORIZONS, f"lr_horizon={self.lr_horizon!r}: choose one of {HORIZONS}")
        _check(
            self.navigation.steps > 0, "navigation.steps must be > 0: the recipe trains a navigating agent"
        )
        _check(
            not (self.grounding_from and self.grounding.steps == 0),
            f"grounding_from={self.grounding_from!r} but grounding.steps=0: this recipe trains without a grounding "
            "stage, so there is none to share; drop one of the two",
        )
        _check(
            self.model is None or resolve_config_path(self.model).is_file(),
            f"model={self.model}: no such file",
        )
        for name, stage in (
            ("grounding", self.grounding),
            ("navigation", self.navigation),
            ("dagger.train", self.dagger.train),
            ("rl", self.rl),
        ):
            stage_train_config(self, stage, name)

    def stage_flags(self, stage: StageBudget) -> list[str]:
        """The train.py options that `model` and a stage's `overrides` add to the stage's command."""
        model = [f"--model={resolve_config_path(self.model)}"] if self.model else []
        return model + [
            f"--{key}={_flag_value(value)}" for key, value in flat_settings(stage.overrides).items()
        ]


def stage_train_config(cfg: RecipeConfig, stage: StageBudget, name: str) -> TrainConfig:
    """train_config with `model` and the stage's overrides, as train.py reads them (the recipe's own options, such
    as the data root and the steps, left out).

    Raises:
        ValueError: one line naming the stage, for an override that names no train.py option or a value it
            refuses.
    """
    args = ["--config_path", str(resolve_config_path(cfg.train_config)), *cfg.stage_flags(stage)]
    try:
        return parse_config(TrainConfig, args)
    except (ValueError, FileNotFoundError, draccus.utils.ParsingError) as err:
        raise ValueError(f"{name}.overrides: train.py: {root_cause(err)}") from None


def _flag_value(value: Any) -> str:
    """A YAML value as train.py's command line writes it (`true`, `[a,b]`, `null`)."""
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return "null"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_flag_value(v) for v in value) + "]"
    return str(value)

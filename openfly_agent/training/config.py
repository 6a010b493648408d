"""`TrainConfig`: every knob of a training run, nested by component and checked on construction.

Leaf module (dataclasses, constants and the model/data config leaves only), so parsing a config never imports
torch. YAML files in `configs/train/` override the defaults; `--a.b=c` flags override the YAML.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

from openfly_agent.constants import STAGE_GROUNDING, STAGE_NAVIGATION, STAGE_RL
from openfly_agent.data.config import DataConfig
from openfly_agent.model.config import LoraSettings, ModelConfig, tiny_config

PRECISIONS = ("no", "bf16", "fp16")
STAGES = (STAGE_GROUNDING, STAGE_NAVIGATION, STAGE_RL)
SCHEDULES = ("constant", "cosine", "linear")
HORIZONS = ("steps", "time")  # where the lr decay ends: the step budget, or whichever of steps and time first
TRACKERS = ("tensorboard", "wandb", "none")
# what `checkpoint.keep_best` may follow: the validation figures (training/evaluate.py); a loss is best lowest
KEEP_BEST_METRICS = ("val/loss", "val/action_accuracy", "val/box_iou")


# Settings that left the training config and what took their place. A run's stored train_config.json that holds
# one reads without it (`without_removed_settings`); a resume compares only the settings both configs have.
REMOVED_SETTINGS = {
    "stop_after_steps": "the test-only OPENFLY_STOP_AFTER_STEPS environment variable (training/stops.py)",
    "tokenizer.path": "model.llm.tokenizer_path",
    "init.format": "read from the folder's config.json",
    "data.train_split": "the train split",
    "logging.run_name": "the output folder's name",
}


def without_removed_settings(stored: dict) -> dict:
    """A stored training config (as `utils.config.config_to_dict` wrote it) without the `REMOVED_SETTINGS`."""
    out = copy.deepcopy(stored)
    for dotted in REMOVED_SETTINGS:
        *sections, name = dotted.split(".")
        node = out
        for section in sections:
            node = node.get(section) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(name, None)
    return out


class BatchSizeError(ValueError):
    """The global batch does not split evenly over processes x per-device batch x accumulation."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


@dataclass
class TokenizerConfig:
    """The tokenizer a tiny-LLM run trains when it has none.

    Where the text tokenizer comes from, in order: the model's `llm.tokenizer_path`; else the init checkpoint's
    folder when it has tokenizer files; else `<output_dir>/tokenizer` from an earlier run; else (tiny LLM only)
    a BPE tokenizer trained on the train split's instructions and saved there.
    """

    train_vocab_size: int = 1024  # BPE vocabulary when one is trained

    def __post_init__(self) -> None:
        vocab = self.train_vocab_size
        _require(vocab >= 64, f"tokenizer.train_vocab_size={vocab}: use >= 64")


@dataclass
class InitConfig:
    """Weights to start from (None: random init from the model config, the tiny default).

    `matching` loads every tensor of one of our checkpoints whose name and shape the configured model shares and
    leaves the rest freshly initialised, listing both: how a stage starts from the previous one (the navigation
    stage from the grounding stage, a DAgger round from the navigation stage) when the model gains modules.
    The format is read from the folder: ours when its config.json has our `model_type`, else OpenVLA's.
    """

    checkpoint: str | None = (
        None  # an OpenFly-Agent / OpenVLA HF folder, or one of our checkpoints (run folders too)
    )
    matching: bool = False  # ours only: load the tensors of matching name and shape, list the new ones


@dataclass
class OptimConfig:
    """AdamW and the learning-rate schedule (per optimizer step)."""

    lr: float = 3e-4  # peak learning rate (after warmup)
    weight_decay: float = 0.0  # applied to matrices only
    betas: tuple[float, float] = (0.9, 0.95)  # AdamW betas
    eps: float = 1e-8  # AdamW epsilon
    schedule: str = "cosine"  # constant | cosine | linear
    warmup_steps: int = 0
    min_lr_ratio: float = 0.0  # floor of cosine / linear as a fraction of lr
    # where the decay ends: `steps`, or `time`: at `steps` or at `time_limit_minutes`, whichever comes first
    # (a run that its time limit cuts still ends at the floor; the recipe's stages have time budgets)
    horizon: str = "steps"
    max_grad_norm: float | None = 1.0  # None disables clipping
    # an exponential moving average of the weights (training/ema.py): validation, the test evaluation and every
    # checkpoint's model folder use it; e.g. 0.999 (warmed up); None: the live weights
    ema_decay: float | None = None
    # PyTorch's fused AdamW kernel on CUDA (ignored on the CPU); false: the default for-each kernel, whose
    # numbers the fused one matches up to rounding
    fused_adamw: bool = False

    def __post_init__(self) -> None:
        _require(self.lr > 0, f"optim.lr must be > 0, got {self.lr}")
        _require(self.weight_decay >= 0, f"optim.weight_decay must be >= 0, got {self.weight_decay}")
        _require(all(0 <= b < 1 for b in self.betas), f"optim.betas must be in [0, 1), got {self.betas}")
        _require(self.schedule in SCHEDULES, f"optim.schedule={self.schedule!r}: choose one of {SCHEDULES}")
        _require(self.horizon in HORIZONS, f"optim.horizon={self.horizon!r}: choose one of {HORIZONS}")
        _require(self.warmup_steps >= 0, f"optim.warmup_steps must be >= 0, got {self.warmup_steps}")
        _require(
            0 <= self.min_lr_ratio <= 1, f"optim.min_lr_ratio must be in [0, 1], not {self.min_lr_ratio}"
        )
        _require(
            self.max_grad_norm is None or self.max_grad_norm > 0,
            f"optim.max_grad_norm must be > 0 or null, got {self.max_grad_norm}",
        )
        _require(
            self.ema_decay is None or 0 < self.ema_decay < 1,
            f"optim.ema_decay must be in (0, 1) or null, got {self.ema_decay}",
        )


@dataclass
class BatchConfig:
    """Batch sizes; gradient accumulation is derived: global / (per_device x processes)."""

    global_batch_size: int = 16  # samples per optimizer step, over all processes and accumulation steps
    per_device_batch_size: int = 8  # samples per forward on each process

    def __post_init__(self) -> None:
        _require(self.per_device_batch_size > 0, "batch.per_device_batch_size must be > 0")
        if self.global_batch_size <= 0 or self.global_batch_size % self.per_device_batch_size:
            raise BatchSizeError(
                f"batch.global_batch_size={self.global_batch_size} is not a positive multiple of "
                f"batch.per_device_batch_size={self.per_device_batch_size}"
            )

    def accumulation_steps(self, world_size: int) -> int:
        """Micro-batches per optimizer step on each process; raises `BatchSizeError` if it does not divide."""
        per_step = self.per_device_batch_size * world_size
        if self.global_batch_size % per_step:
            multiples = [per_step * k for k in (1, 2, 4, 8)]
            raise BatchSizeError(
                f"batch.global_batch_size={self.global_batch_size} does not divide by per_device_batch_size "
                f"({self.per_device_batch_size}) x processes ({world_size}) = {per_step}; use a global batch "
                f"such as {multiples} or change --batch.per_device_batch_size / the number of processes"
            )
        return self.global_batch_size // per_step


@dataclass
class LoraTrainingConfig(LoraSettings):
    """peft LoRA on the LLM (model/language/lora.py), used when `freeze_stage=lora`: adapters, projector and grounding head
    train.

    Inherits rank, alpha, dropout, target_modules ("all-linear" or comma-separated names) and init from the
    model's `LoraSettings`.
    """

    merge_at_end: bool = True  # also write <output_dir>/merged: full weights, merged on rank 0 on the CPU


@dataclass
class LoggingConfig:
    """Trackers (a `metrics.jsonl` is always written) and how often the train metrics are logged. A run's name
    in its trackers is its output folder's name."""

    tracker: str = "tensorboard"  # tensorboard | wandb | none
    project: str = "openfly-agent"  # tracker project name (W&B project, TensorBoard run group)
    log_interval: int = 10  # optimizer steps between log lines

    def __post_init__(self) -> None:
        _require(self.tracker in TRACKERS, f"logging.tracker={self.tracker!r}: choose one of {TRACKERS}")
        _require(self.log_interval > 0, f"logging.log_interval must be > 0, got {self.log_interval}")


@dataclass
class ValidationConfig:
    """Offline action accuracy and box IoU on held-out samples."""

    interval: int = 200  # optimizer steps between validation passes (0: never during training)
    max_samples: int | None = 256  # evenly spaced subset of the validation split (None: all)
    final_max_samples: int | None = None  # the final pass on data.test_split (None: all)
    final_eval: bool = True  # evaluate data.test_split at the end and print the figures
    per_device_batch_size: int | None = (
        None  # evaluation batch per process (None: batch.per_device_batch_size)
    )

    def __post_init__(self) -> None:
        _require(self.interval >= 0, f"validation.interval must be >= 0, got {self.interval}")
        for name in ("max_samples", "final_max_samples", "per_device_batch_size"):
            value = getattr(self, name)
            _require(value is None or value > 0, f"validation.{name} must be > 0 or null, got {value}")


@dataclass
class CheckpointConfig:
    """Periodic checkpoints under `<output_dir>/checkpoints/` (one is always written at the end)."""

    save_interval: int = 500  # optimizer steps (0: only at the end)
    keep_last: int = 3
    # a validation figure (KEEP_BEST_METRICS): each validation pass that beats the best so far (lower loss,
    # higher accuracy / IoU) saves a checkpoint and points `checkpoints/best` at it; null: off
    keep_best: str | None = None

    def __post_init__(self) -> None:
        _require(self.save_interval >= 0, f"checkpoint.save_interval must be >= 0, got {self.save_interval}")
        _require(self.keep_last >= 1, f"checkpoint.keep_last must be >= 1, got {self.keep_last}")
        _require(
            self.keep_best is None or self.keep_best in KEEP_BEST_METRICS,
            f"checkpoint.keep_best={self.keep_best!r}: choose one of {KEEP_BEST_METRICS} (or null)",
        )


@dataclass
class RLConfig:
    """The RL stage (`stage=rl`, training/rl_trainer.py): GRPO on the simulator's own success, from a navigation
    checkpoint (`init.checkpoint`). One update = `episodes_per_update` train episodes x `group_size` sampled
    rollouts each, then `epochs` x `minibatches` optimizer steps on their steps. The run makes `steps` updates at
    `optim.lr` (the schedule steps once per update, so `optim.warmup_steps` counts updates); docs/TRAINING.md, "The RL stage"."""

    group_size: int = 4  # G: rollouts from the same start and instruction (one group)
    episodes_per_update: int = 4  # groups per update (train episodes, drawn anew each update)
    temperature: float = 1.0  # actions sampled from softmax(logits / temperature); log-probs use the same
    clip_epsilon: float = 0.2  # PPO ratio clip: [1 - eps, 1 + eps]
    kl_coef: float = 0.05  # weight of the k3 KL estimate to the starting (reference) policy
    grounding_weight: float = 1.0  # grounding loss on the rollout steps where the simulator sees the target
    epochs: int = 1  # passes over an update's steps
    minibatches: int = 2  # optimizer steps per pass (each over 1 / minibatches of the steps)
    profile: str = "standard"  # the metric profile whose success is the reward (docs/METRICS.md)
    max_steps: int | None = None  # actions per rollout at most (None: the profile's)
    num_envs: int = 8  # lockstep simulator slots (a group's rollouts fly together)
    # shaping terms, each off at 0 (the reward is success alone unless one measurably helps):
    progress_weight: float = 0.0  # x (start distance - final distance) / start distance to the goal
    collision_penalty: float = 0.0  # subtracted once when a move collided
    far_stop_penalty: float = 0.0  # subtracted for a STOP outside the profile's success radius

    def __post_init__(self) -> None:
        for name in ("group_size", "episodes_per_update", "epochs", "minibatches", "num_envs"):
            _require(getattr(self, name) >= 1, f"rl.{name} must be >= 1, got {getattr(self, name)}")
        _require(
            self.group_size >= 2,
            f"rl.group_size must be >= 2 (advantages are within a group), got {self.group_size}",
        )
        _require(
            self.temperature > 0, f"rl.temperature must be > 0 (actions are sampled), got {self.temperature}"
        )
        _require(self.clip_epsilon > 0, f"rl.clip_epsilon must be > 0, got {self.clip_epsilon}")
        for name in (
            "kl_coef",
            "grounding_weight",
            "progress_weight",
            "collision_penalty",
            "far_stop_penalty",
        ):
            _require(getattr(self, name) >= 0, f"rl.{name} must be >= 0, got {getattr(self, name)}")
        _require(
            self.max_steps is None or self.max_steps >= 1,
            f"rl.max_steps must be >= 1 or null, got {self.max_steps}",
        )


@dataclass
class TrainConfig:
    """A training run. `configs/train/*.yaml` are instances of it; `train.py --help` lists every field that applies
    to the run it describes (training/cli.py::unlisted)."""

    model: ModelConfig = field(default_factory=tiny_config)
    data: DataConfig = field(default_factory=DataConfig)
    tokenizer: TokenizerConfig = field(default_factory=TokenizerConfig)
    init: InitConfig = field(default_factory=InitConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    batch: BatchConfig = field(default_factory=BatchConfig)
    lora: LoraTrainingConfig = field(default_factory=LoraTrainingConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    rl: RLConfig = field(default_factory=RLConfig)  # the RL stage's settings (stage=rl only)

    # grounding: referring expressions + instruction targets, no action loss (data.grounding_root);
    # navigation: actions and the grounding loss on the navigation dataset; rl: GRPO in the simulator from a
    # navigation checkpoint, `steps` updates (the `rl` section) (docs/TRAINING.md, "Stages")
    stage: str = "navigation"
    precision: str = "no"  # no | bf16 | fp16 (autocast; overrides the accelerate config file's value)
    gradient_checkpointing: bool = False  # activation checkpointing inside the LLM and ViTs
    compile_layers: bool = (
        False  # torch.compile each LLM decoder layer (training/modes.py; compiles on first use)
    )
    freeze_stage: str = "full"  # full | frozen_vision | heads_only | lora (LoRA adapters, the `lora` section)
    steps: int | None = None  # optimizer steps of the run (wins over `epochs` when both are set)
    epochs: float | None = 1.0  # passes over the train split, used when `steps` is null
    # also stop (and save) once this much training time has passed, counted over resumes
    time_limit_minutes: float | None = None
    # run folder (checkpoints/, logs/, tokenizer/), relative to the working directory
    output_dir: str = "outputs/train/tiny"
    seed: int = 7  # model init, data order and augmentation
    resume: bool = False  # continue from <output_dir>/checkpoints/last
    cpu: bool = False  # train on the CPU even when CUDA is present

    def __post_init__(self) -> None:
        _require(self.precision in PRECISIONS, f"precision={self.precision!r}: choose one of {PRECISIONS}")
        _require(self.stage in STAGES, f"stage={self.stage!r}: choose one of {STAGES}")
        _require(
            self.stage != STAGE_GROUNDING or self.data.grounding_root is not None,
            "stage=grounding trains on a grounding dataset: set --data.grounding_root "
            "(python -m openfly_agent.toolchain grounding writes one)",
        )
        _require(
            self.stage != STAGE_GROUNDING or self.model.grounding.has_head,
            "stage=grounding trains the grounding head: model.grounding.type must name one, not none",
        )
        _require(
            self.stage != STAGE_RL or (self.init.checkpoint is not None and self.steps is not None),
            "stage=rl fine-tunes a navigation checkpoint: set --init.checkpoint and --steps (the updates)",
        )
        _require(
            self.steps is not None or self.epochs is not None,
            "set `steps` (optimizer steps) or `epochs` (passes over the train split)",
        )
        _require(self.steps is None or self.steps > 0, f"steps must be > 0, got {self.steps}")
        _require(self.epochs is None or self.epochs > 0, f"epochs must be > 0, got {self.epochs}")
        _require(
            self.time_limit_minutes is None or self.time_limit_minutes > 0,
            f"time_limit_minutes must be > 0 or null, got {self.time_limit_minutes}",
        )
        _require(
            self.optim.horizon != "time" or self.time_limit_minutes is not None,
            "optim.horizon=time decays the lr over the time budget: set --time_limit_minutes",
        )
        _require(
            self.checkpoint.keep_best is None or self.validation.interval > 0,
            f"checkpoint.keep_best={self.checkpoint.keep_best} follows validation: set --validation.interval > 0",
        )

    @property
    def use_lora(self) -> bool:
        """LoRA runs are the runs of freeze stage `lora` (adapters + projector + grounding head train)."""
        return self.freeze_stage == "lora"

"""Typed options of the data part: how released labels are read, and how training samples are built.

Leaf module (stdlib + constants only) so run configs can compose it without importing torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from openfly_agent import constants as C

TAKEOFF_LANDING_MODES = ("keep", "map", "trim")
MERGED_FORWARD_POSITIONS = ("end", "start")
HISTORY_MODES = ("keyframes", "uniform", "random", "none")


@dataclass
class ReaderOptions:
    """How annotation records become `Episode`s (data_cards/openfly_released.md explains each choice).

    Attributes:
        takeoff_landing: what to do with the -1 (take-off climb) / -2 (landing descent) phases.
            "keep": leave them (training skips those steps, they still serve as history frames);
            "map": -1 -> 4 (ascend) in place, and the released "0, -2, ..., -2" tail becomes
            "5, ..., 5, 0": each descent label moves to the frame where that descent starts and STOP
            goes to the landed frame (the order the official toolchain writes, docs/OFFICIAL_OPENFLY.md 7.4);
            "trim": drop the -1 frames and the -2 frames; the episode ends at its STOP frame, which
            also becomes the goal.
        merged_forward_position: where merged 6 / 9 m labels (8 / 9) sit. "end" = as released (on the
            last raw frame of the merged block). "start" = relabel every forward frame (1 / 8 / 9) with
            the forward move that its pose -> next pose displacement shows (3 / 6 / 9 m), so a label
            describes the motion that starts at its frame; frames whose displacement is not a pure
            forward move keep their label (see data/labels.py).
        strict: raise `SchemaError` on the first bad record (True) or log it, skip the episode and
            collect it in the read report (False).
    """

    takeoff_landing: str = "trim"
    merged_forward_position: str = "end"
    strict: bool = True

    def __post_init__(self) -> None:
        if self.takeoff_landing not in TAKEOFF_LANDING_MODES:
            choices = TAKEOFF_LANDING_MODES
            raise ValueError(
                f"ReaderOptions.takeoff_landing={self.takeoff_landing!r}: choose one of {choices}"
            )
        if self.merged_forward_position not in MERGED_FORWARD_POSITIONS:
            raise ValueError(
                f"ReaderOptions.merged_forward_position={self.merged_forward_position!r}: "
                f"choose one of {MERGED_FORWARD_POSITIONS}"
            )


@dataclass
class HistoryConfig:
    """Which earlier frames a training sample carries as memory.

    How many (K) and how large (S) the memory sets are is the model's: `model.memory.capacity` and the
    keyframe set size `2 x model.keyframes.radius + 1`; training passes them to the dataset.

    Attributes:
        mode: "keyframes" (the injected keyframe selector), "uniform" (K single frames evenly spaced over
            the frames before t), "random" (K random earlier frames, reproducible per sample and epoch) or
            "none".
    """

    mode: str = "keyframes"

    def __post_init__(self) -> None:
        if self.mode not in HISTORY_MODES:
            raise ValueError(f"data.history.mode={self.mode!r}: choose one of {HISTORY_MODES}")


@dataclass
class DataConfig:
    """Where the dataset lives, its splits, and how samples are read and drawn from it. Training reads the `train`
    split (and that of each `extra_train_roots` dataset).

    Attributes:
        root: dataset root (`traj/`, `Annotation/`, `meta/`), released OpenFly or generated; relative to the
            working directory.
        val_split: periodic validation and `checkpoint.keep_best` (what choices are made on). The default `val` is
            the generated datasets' validation split; a dataset without one (the released OpenFly data, datasets
            generated before it existed) validates on `test_seen` instead, with a warning in the run's log.
        test_split: the final offline evaluation, read by nothing before it.
        reader: label handling (ReaderOptions).
        history: memory frames per sample (HistoryConfig).
        num_workers: DataLoader worker processes per training process.
        cache_episodes: episodes whose encoded frames stay in memory per process (LRU).
        cache_frames: decoded frames kept per process (LRU).
        extra_train_roots: more datasets (same layout) whose train split joins the training data, e.g. the
            DAgger rounds' rollouts (their frames are read from their own roots).
        grounding_root: the grounding dataset (`toolchain grounding`) the grounding stage trains on.
        instruction_fraction: grounding stage: share of its samples that are navigation steps (instruction and
            target box) rather than referring expressions.
        expressions_per_frame: grounding stage: expressions per grounding frame in a batch (one encode each).
    """

    # dataset root (relative to the working directory); the toolchain writes embedded-small there
    root: str = "outputs/datasets/embedded-small"
    val_split: str = C.SPLIT_VAL
    test_split: str = C.SPLIT_TEST_UNSEEN
    reader: ReaderOptions = field(default_factory=ReaderOptions)
    history: HistoryConfig = field(default_factory=HistoryConfig)
    num_workers: int = 0
    cache_episodes: int = 8
    cache_frames: int = 256
    extra_train_roots: list[str] = field(default_factory=list)
    grounding_root: str | None = None
    instruction_fraction: float = 0.25
    expressions_per_frame: int = 4

    def __post_init__(self) -> None:
        if not 0.0 <= self.instruction_fraction < 1.0:
            raise ValueError(f"data.instruction_fraction={self.instruction_fraction} must be in [0, 1)")
        if self.expressions_per_frame < 1:
            raise ValueError(f"data.expressions_per_frame={self.expressions_per_frame} must be >= 1")
        for name in ("val_split", "test_split"):
            value = getattr(self, name)
            if value not in C.SPLITS:
                raise ValueError(f"data.{name}={value!r}: choose one of {C.SPLITS}")
        if self.num_workers < 0:
            raise ValueError(f"data.num_workers={self.num_workers} must be >= 0")
        if self.cache_episodes < 1 or self.cache_frames < 1:
            raise ValueError("data.cache_episodes and data.cache_frames must be >= 1")

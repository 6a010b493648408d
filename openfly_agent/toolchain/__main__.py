"""Command line of the data toolchain (`python -m openfly_agent.toolchain`, or `openfly-generate`).

`generate` / `dagger` take every GenerateConfig field as a dotted override (`--render.width=96`); `<command>
--help` lists them with the values a plain run uses. Exit codes: 0 done, 2 bad input (one line on stderr,
e.g. a folder that holds a dataset of other settings), 130 interrupted (rerun the same command to resume).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.rollout.agent import AgentPolicy
from openfly_agent.rollout.checkpoints import CheckpointError, load_agent
from openfly_agent.toolchain.config import DaggerRoundConfig, GenerateConfig, GroundingDataConfig, parse_shard
from openfly_agent.toolchain.dagger_rounds import run_dagger_round
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.grounding import generate_grounding
from openfly_agent.toolchain.landmarks import write_landmark_list
from openfly_agent.toolchain.pipeline import KIND_DAGGER_POLICY, prepare_scene
from openfly_agent.toolchain.scenes import generate_config_for_real_scene, real_scene
from openfly_agent.toolchain.settings import GenerateSettingsError
from openfly_agent.toolchain.summary import empty_splits_message, write_summary
from openfly_agent.utils.cli_help import choose_command, command_help, commands_usage, wants_help
from openfly_agent.utils.cli_options import CommandLineError
from openfly_agent.utils.config import REPO_ROOT, parse_config, with_config_path
from openfly_agent.utils.errors import root_cause
from openfly_agent.utils.logging_utils import setup_logging

PROG = "python -m openfly_agent.toolchain"
COMMANDS = {
    "generate": "scenes -> an OpenFly-format dataset (resumable, sharded with --shard i/N)",
    "summarize": "merge copied shards into one dataset and write its summary",
    "dagger": "DAgger episodes flown by a trained agent, relabelled by the A* expert, added to a dataset",
    "segment": "BEV landmark segmentation of a real scene's point cloud into an official landmark list",
    "grounding": "referring expressions (one per visible landmark) on rendered frames of a dataset's cities",
    "dagger-round": "one DAgger round: a trained agent flies train episodes in lockstep, the A* expert labels "
    "every visited state, the rollouts are written as a new dataset",
}
EXAMPLES = {
    "generate": (
        f"{PROG} generate --config_path configs/toolchain/embedded-small.yaml        # < 1 min on 2 cores",
        f"{PROG} generate --config_path configs/toolchain/embedded-100k.yaml --shard 3/16",
        f"{PROG} generate --config_path configs/toolchain/embedded-small.yaml --render.width=96 "
        "--render.height=96 --output_dir=outputs/datasets/small-96",
    ),
    "summarize": (
        f"{PROG} summarize --root outputs/datasets/embedded-100k    # after copying the shards together",
    ),
    "dagger": (
        f"{PROG} dagger --config_path configs/toolchain/embedded-small.yaml --checkpoint outputs/train/tiny "
        "--dagger.episodes_per_scene=4",
    ),
    "segment": (f"{PROG} segment --env_yaml env_x.yaml --point_cloud x.pcd --out seg_map_x.jsonl",),
    "grounding": (
        f"{PROG} grounding --source_root outputs/datasets/embedded-small "
        "--output_dir outputs/datasets/grounding-small",
    ),
    "dagger-round": (
        f"{PROG} dagger-round --checkpoint outputs/recipe/navigation --source_root outputs/datasets/embedded-small "
        "--output_dir outputs/datasets/dagger-r1 --episodes 400",
    ),
}
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
# The dataset of a plain `generate` (train.py's default `data.root`): the one source of its settings.
DEFAULT_GENERATE_CONFIG = REPO_ROOT / "configs" / "toolchain" / "embedded-small.yaml"


class InputError(Exception):
    """Bad input of a command; the message is printed as one line and the exit code is 2."""


def _usage() -> str:
    examples = [example for command_examples in EXAMPLES.values() for example in command_examples]
    return commands_usage(
        PROG, "The OpenFly data toolchain (docs/TOOLCHAIN.md).", COMMANDS, examples, options="[options]"
    )


def _generate_args(args: list[str]) -> list[str]:
    """`args` with DEFAULT_GENERATE_CONFIG when they name no --config_path: a plain `generate` writes exactly the
    dataset of configs/toolchain/embedded-small.yaml under its name."""
    return with_config_path(args, DEFAULT_GENERATE_CONFIG)


def _parse_generate(args: list[str]):
    """GenerateConfig from YAML (default: DEFAULT_GENERATE_CONFIG) + overrides; a bad value or option is an
    InputError naming the field."""
    return _parse_command_config(GenerateConfig, _generate_args(args), "generate")


def _generate_help(command: str, args: list[str], config_class: type = GenerateConfig) -> str:
    description = COMMANDS[command] + (
        ". Relative paths are relative to the working directory; a --config_path under configs/ not found there "
        "is read from the repository."
    )
    return command_help(
        config_class, _generate_args(args), f"{PROG} {command}", description, EXAMPLES[command],
        placeholders=CHECKPOINT_PLACEHOLDER if config_class is not GenerateConfig else None,
    )  # fmt: skip


def cmd_generate(args: list[str]) -> None:
    if wants_help(args):
        print(_generate_help("generate", args), end="")
        return
    cfg = _parse_generate(args)
    setup_logging()
    try:
        summary = generate(cfg)
    except GenerateSettingsError as err:
        raise InputError(str(err)) from None
    print(json.dumps({k: summary[k] for k in ("trajectories", "per_split", "rejected", "vocabulary_size")}))
    empty = empty_splits_message(summary)
    if empty:  # eval and training stop on an empty split: said here, not when they do
        shard = f" (shard {cfg.shard})" if parse_shard(cfg.shard)[1] > 1 else ""
        print(f"{PROG} generate: warning{shard}: {empty}", file=sys.stderr)


@dataclass
class SummarizeConfig:
    """`summarize`: merge copied shards into one dataset and write its summary."""

    root: str = ""  # dataset root holding one or more copied shards
    plots: bool = True  # draw summary.png

    def __post_init__(self) -> None:
        if not self.root:
            raise ValueError("--root is required: the dataset root holding the copied shards")


@dataclass
class SegmentConfig:
    """`segment`: BEV landmark segmentation of a real scene's point cloud into an official landmark list."""

    env_yaml: str = ""  # the scene's official env_*.yaml
    point_cloud: str = ""  # .pcd (ASCII or binary) or .ply
    out: str = ""  # landmark list to write (official seg_map JSONL)

    def __post_init__(self) -> None:
        for name in ("env_yaml", "point_cloud", "out"):
            if not getattr(self, name):
                raise ValueError(f"--{name} is required (segment --help lists the options)")


def cmd_summarize(args: list[str]) -> None:
    if wants_help(args):
        print(
            command_help(
                SummarizeConfig, args, f"{PROG} summarize", COMMANDS["summarize"], EXAMPLES["summarize"]
            ),
            end="",
        )
        return
    cfg = _parse_command_config(SummarizeConfig, args, "summarize")
    setup_logging()
    OpenFlyDatasetWriter(cfg.root).finalize()
    print(json.dumps(write_summary(cfg.root, plots=cfg.plots), indent=2))


def _agent_session(checkpoint: str):
    """A closed-loop session of the agent behind `checkpoint` (a folder, a training run or its pointer, or a Hub
    id), on the CPU."""
    try:
        return load_agent(checkpoint, "cpu").new_session()
    except (FileNotFoundError, CheckpointError) as err:
        raise InputError(str(err)) from None


CHECKPOINT_PLACEHOLDER = {"checkpoint": "x"}  # lets --help parse a command line without its --checkpoint


def _require_checkpoint(checkpoint: str, command: str) -> None:
    if not checkpoint:
        raise ValueError(
            f"--checkpoint is required: the trained agent folder (or Hub id) that flies the episodes ({command} "
            "--help lists the options)"
        )


@dataclass
class DaggerCommandConfig(GenerateConfig):
    """`dagger`: a dataset's settings (GenerateConfig) and the trained agent that flies its DAgger episodes."""

    checkpoint: str = ""  # trained agent folder (or Hub id) that flies the DAgger episodes (required)

    def __post_init__(self) -> None:
        super().__post_init__()
        _require_checkpoint(self.checkpoint, "dagger")


@dataclass
class DaggerRoundCommandConfig(DaggerRoundConfig):
    """`dagger-round`: one round's settings (DaggerRoundConfig), the agent that flies it and its threads."""

    checkpoint: str = ""  # trained agent folder (or Hub id) that flies the rollouts (required)
    torch_threads: int = 0  # torch threads of the rollouts (0: torch's default)

    def __post_init__(self) -> None:
        super().__post_init__()
        _require_checkpoint(self.checkpoint, "dagger-round")
        if self.torch_threads < 0:
            raise ValueError(f"torch_threads must be >= 0 (0: torch's default), got {self.torch_threads}")


def _as_base(cfg, base_class):
    """The `base_class` part of a command's config (the settings a dataset records, without the command's own)."""
    return base_class(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(base_class)})


def cmd_dagger(args: list[str]) -> None:
    if wants_help(args):
        print(_generate_help("dagger", args, DaggerCommandConfig), end="")
        return
    cfg = _parse_command_config(DaggerCommandConfig, _generate_args(args), "dagger")
    setup_logging()
    policy = AgentPolicy(_agent_session(cfg.checkpoint))
    try:
        summary = generate(_as_base(cfg, GenerateConfig), policy=policy, kinds=(KIND_DAGGER_POLICY,))
    except GenerateSettingsError as err:
        raise InputError(str(err)) from None
    print(json.dumps({k: summary[k] for k in ("trajectories", "dagger_episodes", "rejected")}))


def cmd_segment(args: list[str]) -> None:
    if wants_help(args):
        print(
            command_help(SegmentConfig, args, f"{PROG} segment", COMMANDS["segment"], EXAMPLES["segment"]),
            end="",
        )
        return
    cfg = _parse_command_config(SegmentConfig, args, "segment")
    setup_logging()
    scene_cfg = generate_config_for_real_scene(cfg.env_yaml, segment=True)
    prepared = prepare_scene(real_scene(cfg.env_yaml, cfg.point_cloud), scene_cfg)
    write_landmark_list(Path(cfg.out), list(prepared.landmarks.values()), scene_cfg.map.pcd_scale_ratio)
    print(json.dumps({"landmarks": len(prepared.landmarks), "out": cfg.out}))


def _parse_command_config(config_class, args: list[str], command: str):
    """A command's config dataclass from `args`; bad input is a one-line InputError."""
    import draccus

    try:
        return parse_config(config_class, args)
    except CommandLineError as err:
        raise InputError(str(err)) from None
    except draccus.utils.ParsingError as err:
        raise InputError(f"bad {command} config: {root_cause(err)}") from None


def cmd_grounding(args: list[str]) -> None:
    if wants_help(args):
        description = COMMANDS["grounding"] + " (data_cards/grounding.md); resumable scene by scene"
        print(
            command_help(GroundingDataConfig, args, f"{PROG} grounding", description, EXAMPLES["grounding"]),
            end="",
        )
        return
    cfg = _parse_command_config(GroundingDataConfig, args, "grounding")
    setup_logging()
    try:
        info = generate_grounding(cfg)
    except FileNotFoundError as err:
        raise InputError(str(err)) from None
    print(json.dumps(info["splits"]))


def cmd_dagger_round(args: list[str]) -> None:
    if wants_help(args):
        text = command_help(
            DaggerRoundCommandConfig, args, f"{PROG} dagger-round --checkpoint DIR", COMMANDS["dagger-round"],
            EXAMPLES["dagger-round"], placeholders=CHECKPOINT_PLACEHOLDER,
        )  # fmt: skip
        print(text, end="")
        return
    cfg = _parse_command_config(DaggerRoundCommandConfig, args, "dagger-round")
    setup_logging()
    if cfg.torch_threads:
        import torch

        torch.set_num_threads(cfg.torch_threads)
    policy = AgentPolicy(_agent_session(cfg.checkpoint))
    print(json.dumps(run_dagger_round(policy, _as_base(cfg, DaggerRoundConfig))))


HANDLERS = {
    "generate": cmd_generate,
    "summarize": cmd_summarize,
    "dagger": cmd_dagger,
    "segment": cmd_segment,
    "grounding": cmd_grounding,
    "dagger-round": cmd_dagger_round,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    chosen = choose_command(list(sys.argv[1:] if argv is None else argv), list(COMMANDS), PROG, _usage())
    if isinstance(chosen, int):
        return chosen
    command, args = chosen
    try:
        HANDLERS[command](args)
    except InputError as err:
        print(f"{PROG} {command}: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG} {command}: interrupted; run the same command again to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())

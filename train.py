"""Train OpenFly-Agent, from one CPU to a GPU cluster (docs/TRAINING.md).

Parses the config, generates the dataset when it is missing, builds the run (all input checks first) and
calls `training.fit`. Prints the final offline action accuracy next to the majority-class rate. Exit codes:
0 done (or stopped by SIGTERM / SIGUSR1 with a checkpoint), 2 bad input or unreadable data (one line on
stderr), 130 interrupted (Ctrl-C). `python train.py --help` lists every option with the value a plain run
uses.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent
DEFAULT_CONFIG = REPO_ROOT / "configs" / "train" / "tiny.yaml"
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C

DESCRIPTION = (
    "Train OpenFly-Agent with accelerate, from one CPU to many GPUs (docs/TRAINING.md). Without --config_path "
    "the tiny preset runs on the embedded-small dataset (generated first when missing). Relative paths are "
    "relative to the working directory; the repository's own configs/ are found from anywhere."
)
EXAMPLES = (
    "accelerate launch train.py                                   # tiny preset, embedded-small data, CPU",
    "accelerate launch train.py --config_path configs/train/tiny.yaml --optim.lr=3e-4 --steps=500",
    "accelerate launch train.py --resume                          # continue <output_dir> from its last checkpoint",
    "accelerate launch --config_file configs/accelerate/fsdp.yaml train.py "
    "--config_path configs/train/openfly-7b-full.yaml --init.checkpoint=/path/to/openvla-7b",
)

logger = logging.getLogger("train")


def with_default_config(argv: list[str]) -> list[str]:
    """`argv` with `--resume` alone meaning `--resume=true`, and the tiny preset when no config is given."""
    argv = ["--resume=true" if arg == "--resume" else arg for arg in argv]
    if not any(arg == "--config_path" or arg.startswith("--config_path=") for arg in argv):
        argv = ["--config_path", str(DEFAULT_CONFIG), *argv]
    return argv


def parse_args(argv: list[str]):
    """`TrainConfig` from `--config_path` (default: the tiny preset) and dotted overrides; `--resume` alone
    means `--resume=true`."""
    from openfly_agent.training.config import TrainConfig
    from openfly_agent.utils.config import parse_config

    return parse_config(TrainConfig, with_default_config(argv))


def help_text(argv: list[str]) -> str:
    """`--help`: every option with the value the same command line without `--help` would use."""
    from openfly_agent.training.config import TrainConfig
    from openfly_agent.utils.cli_help import config_help, config_path_of, without_help

    argv = with_default_config(without_help(argv))
    config = config_path_of(argv)
    try:
        cfg = parse_args(argv)
    except Exception:  # a bad override: show the preset's own values
        cfg = parse_args(["--config_path", config])
    note = f"Defaults below are the values of {config} (and of the overrides given)."
    extra = [("--resume", "same as --resume=true: continue <output_dir> from checkpoints/last")]
    return config_help(TrainConfig, cfg, "train.py", DESCRIPTION, EXAMPLES, note, extra)


def ensure_dataset(cfg) -> None:
    """Generate the dataset with the toolchain when `data.root` has no train split (rank 0; others wait)."""
    from accelerate import PartialState

    from openfly_agent.data.openfly_reader import annotation_path
    from openfly_agent.training.engine import use_cpu

    if annotation_path(cfg.data.root, cfg.data.train_split).is_file() or not cfg.data.generate_if_missing:
        return
    state = PartialState(cpu=use_cpu(cfg))
    with state.main_process_first():
        if state.is_main_process:
            from openfly_agent.toolchain.config import GenerateConfig
            from openfly_agent.toolchain.generate import generate
            from openfly_agent.utils.config import load_yaml_config

            logger.info("%s has no dataset: generating it with %s", cfg.data.root, cfg.data.toolchain_config)
            overrides = [f"--output_dir={cfg.data.root}"]  # write where training reads
            generate(load_yaml_config(GenerateConfig, cfg.data.toolchain_config, overrides))


def report(result, cfg) -> None:
    """The final figures, on stdout of the main process."""
    final = result.final_metrics
    print(f"finished at step {result.state.step}; last checkpoint: {result.checkpoint}")
    if final:
        majority = final.get("majority_class_rate", float("nan"))
        print(
            f"offline action accuracy on {cfg.data.test_split} ({int(final['samples'])} samples): "
            f"{final['action_accuracy']:.4f}; majority-class rate: {majority:.4f}; "
            f"box IoU: {final['box_iou']:.4f}"
        )


def interrupted_message(output_dir: str | None) -> str:
    """What Ctrl-C prints: how to pick the run up again."""
    from openfly_agent.training.checkpoint import CheckpointManager

    latest = CheckpointManager(output_dir, keep_last=1).latest() if output_dir else None
    if latest is None:
        return "train.py: interrupted before the first checkpoint; run the same command again to start over"
    return f"train.py: interrupted; run the same command with --resume to resume from {latest}"


def run(argv: list[str], state: dict) -> int:
    """Parse, check, train and report; `state["output_dir"]` is set as soon as it is known."""
    from draccus.utils import ParsingError

    from openfly_agent.data.schema import SchemaError
    from openfly_agent.training import PreflightError, build_run, fit
    from openfly_agent.utils.cli_help import UnknownOptionError, wants_help
    from openfly_agent.utils.errors import RecordError, one_line, root_cause, worker_error_name
    from openfly_agent.utils.logging_utils import setup_logging

    if wants_help(argv):
        print(help_text(argv), end="")
        return 0
    setup_logging()
    data_errors = (SchemaError, RecordError)
    try:
        cfg = parse_args(argv)
        state["output_dir"] = cfg.output_dir
        ensure_dataset(cfg)
        run = build_run(cfg)
    except (ParsingError, PreflightError, UnknownOptionError) as err:
        print(f"train.py: {root_cause(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except data_errors as err:
        print(f"train.py: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        result = fit(run)
    except data_errors as err:  # a frame or file that fails to read mid-training
        print(f"train.py: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RuntimeError as err:  # the same, raised inside a DataLoader worker
        if worker_error_name(err) not in {e.__name__ for e in data_errors}:
            raise
        print(f"train.py: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if run.accelerator.is_main_process:
        report(result, cfg)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (Ctrl-C: one line and 130, no traceback).

    The process group is closed here, after `run` has returned and released the model, optimizer and loaders
    (utils/distributed.py explains why the order matters).
    """
    from openfly_agent.utils.distributed import close_process_group

    state: dict = {}
    try:
        code = run(list(sys.argv[1:] if argv is None else argv), state)
    except KeyboardInterrupt:
        print(interrupted_message(state.get("output_dir")), file=sys.stderr)
        code = EXIT_INTERRUPTED
    close_process_group(synchronize=code == 0)
    return code


if __name__ == "__main__":
    sys.exit(main())

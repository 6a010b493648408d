"""train.py's command line: the config it parses, its `--help`, and the one-line messages of a run that fails.

train.py stays the short entry point (parse, `train(cfg)`, report); what
it prints for `--help`, for data that cannot be read and for Ctrl-C lives here.
"""

from __future__ import annotations

from openfly_agent.data.schema import SchemaError
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.utils.cli_help import command_help
from openfly_agent.utils.config import REPO_ROOT, parse_config, with_config_path
from openfly_agent.utils.errors import RecordError, one_line, worker_error_name

DEFAULT_CONFIG = REPO_ROOT / "configs" / "train" / "tiny.yaml"

DESCRIPTION = (
    "Train OpenFly-Agent with accelerate, from one CPU to many GPUs (docs/TRAINING.md). Without --config_path "
    "the tiny preset runs on the embedded-small dataset, made beforehand (python -m openfly_agent.toolchain "
    "generate). Relative paths are relative to the working directory; the repository's own configs/ are found "
    "from anywhere."
)
EXAMPLES = (
    "accelerate launch train.py                                   # tiny preset, embedded-small data, CPU",
    "accelerate launch train.py --config_path configs/train/tiny.yaml --optim.lr=3e-4 --steps=500",
    "accelerate launch train.py --resume                          # continue <output_dir> from its last checkpoint",
    "accelerate launch --config_file configs/accelerate/fsdp.yaml train.py "
    "--config_path configs/train/openfly-7b-full.yaml --init.checkpoint=/path/to/openvla-7b "
    "--model.llm.tokenizer_path=/path/to/openvla-7b --data.root=/path/to/OpenFly",
)


def with_default_config(argv: list[str]) -> list[str]:
    """`argv` with the tiny preset when no config is given."""
    return with_config_path(argv, DEFAULT_CONFIG)


def parse_args(argv: list[str]):
    """`TrainConfig` from `--config_path` (default: the tiny preset) and dotted overrides."""
    return parse_config(TrainConfig, with_default_config(argv))


def help_text(argv: list[str]) -> str:
    """`--help`: every option with the value the same command line without `--help` would use."""
    return command_help(TrainConfig, with_default_config(argv), "train.py", DESCRIPTION, EXAMPLES)


def data_error_message(err: BaseException) -> str | None:
    """The one line (file, record, field) of a dataset that cannot be read, or None for any other error.

    Covers the reader's and the frame store's errors raised in this process, before or during training, and
    the same errors raised inside a DataLoader worker (torch re-raises those as a RuntimeError).
    """
    data_errors = (SchemaError, RecordError)
    if isinstance(err, data_errors) or worker_error_name(err) in {e.__name__ for e in data_errors}:
        return one_line(err)
    return None


def interrupted_message(output_dir: str | None) -> str:
    """What Ctrl-C prints: how to pick the run up again."""
    latest = CheckpointManager(output_dir, keep_last=1).latest() if output_dir else None
    if latest is None:
        return "train.py: interrupted before the first checkpoint; run the same command again to start over"
    return f"train.py: interrupted; run the same command with --resume to resume from {latest}"

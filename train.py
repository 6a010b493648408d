"""Train OpenFly-Agent, from one CPU to a GPU cluster (docs/TRAINING.md).

    accelerate launch train.py                                   # tiny preset, embedded-small data, CPU
    accelerate launch train.py --config_path configs/train/tiny.yaml --optim.lr=3e-4 --steps=500
    accelerate launch train.py --resume                      # continue <output_dir> from its last checkpoint
    accelerate launch --config_file configs/accelerate/fsdp.yaml train.py \
        --config_path configs/train/openfly-7b-full.yaml --init.checkpoint=/path/to/openvla-7b \
        --model.llm.tokenizer_path=/path/to/openvla-7b --data.root=/path/to/OpenFly

Parses the config and calls `training.train` (all input checks come first). The dataset is made beforehand
(`python -m openfly_agent.toolchain generate`; the recipe and the main job generate theirs). Prints the final
offline action accuracy next to the majority-class rate. Exit codes: 0 done (or stopped by SIGTERM / SIGUSR1
with a checkpoint), 2 bad input or unreadable data (one line on stderr), 130 interrupted (Ctrl-C). `python train.py --help` lists every option that applies to the run described, with the value it
uses; the help, the did-you-mean and the one-line messages come from `training/cli.py`.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time

from openfly_agent.training.cli import (  # noqa: F401  (parse_args, with_default_config: tests/test_docs.py)
    DEFAULT_CONFIG,
    data_error_message,
    help_text,
    interrupted_message,
    parse_args,
    with_default_config,
)
from openfly_agent.utils.cli_help import wants_help
from openfly_agent.utils.cli_options import CommandLineError
from openfly_agent.utils.distributed import close_process_group
from openfly_agent.utils.errors import root_cause
from openfly_agent.utils.files import first_missing_dir, remove_created_dirs, remove_empty_dirs
from openfly_agent.utils.logging_utils import setup_logging

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C
RANK_ERROR_GRACE_S = 60.0  # how long a process other than rank 0 leaves rank 0 to say an input error
RUN_SUBFOLDERS = ("logs", "checkpoints", "tokenizer")  # what a run creates in its output_dir

logger = logging.getLogger("train")


NO_BOXES = "n/a (no boxes in this data)"  # the box IoU of samples without a visible target box


def report(result, cfg) -> None:
    """The final figures, on stdout of the main process."""
    final = result.final_metrics
    print(f"finished at step {result.state.step}; last checkpoint: {result.checkpoint}")
    if not final:
        return
    iou = final["box_iou"]
    iou_text = NO_BOXES if math.isnan(iou) else f"{iou:.4f}"
    if "action_accuracy" in final:
        majority = final.get("majority_class_rate", float("nan"))
        print(
            f"offline action accuracy on {cfg.data.test_split} ({int(final['samples'])} samples): "
            f"{final['action_accuracy']:.4f}; majority-class rate: {majority:.4f}; box IoU: {iou_text}"
        )
    else:  # the grounding stage: no actions
        print(f"target box IoU on {cfg.data.test_split} ({int(final['samples'])} samples): {iou_text}")


def say_error(message: str) -> None:
    """The one line of an input error on stderr, from the first process only: every process of a launch
    (`RANK`, set by accelerate and torchrun) meets the same error, and one line says it.

    The other processes wait before they exit: the launcher stops the whole launch as soon as one process
    exits, and a process that exited first would cut rank 0 off before its line. Rank 0's exit ends the wait
    (the launcher stops the rest); a process still running after `RANK_ERROR_GRACE_S` met an error rank 0
    did not, and says it itself.
    """
    if int(os.environ.get("RANK", "0")) != 0:
        time.sleep(RANK_ERROR_GRACE_S)
    print(f"train.py: {message}", file=sys.stderr)


def run(argv: list[str], state: dict) -> int:
    """Parse, check, train and report; `state["output_dir"]` is set as soon as it is known."""
    from draccus.utils import ParsingError

    from openfly_agent.training import PreflightError, train  # lazy: torch + transformers; --help stays fast

    if wants_help(argv):
        print(help_text(argv), end="")
        return 0
    setup_logging()
    try:
        cfg = parse_args(argv)
        state["output_dir"] = cfg.output_dir
        state["created"] = first_missing_dir(cfg.output_dir)  # e.g. outputs/: a failed start removes it again
        result = train(cfg)
    except (ParsingError, PreflightError, CommandLineError) as err:
        if "output_dir" in state:  # a failed start leaves no empty run folder (every process: no race)
            remove_empty_dirs(state["output_dir"], RUN_SUBFOLDERS)
            remove_created_dirs(state["output_dir"], state["created"])
        say_error(root_cause(err))
        return EXIT_BAD_INPUT
    except Exception as err:  # data that fails to read, before or during training (also in a loader worker)
        message = data_error_message(err)
        if message is None:
            raise
        print(f"train.py: {message}", file=sys.stderr)  # met by this process only (its share of the data)
        return EXIT_BAD_INPUT
    if result.is_main_process:
        report(result, cfg)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (Ctrl-C: one line and 130, no traceback).

    The process group is closed here, after `run` has returned and released the model, optimizer and loaders
    (utils/distributed.py explains why the order matters).
    """
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

"""Closed-loop evaluation of a checkpoint (and baselines) on the test-seen / test-unseen splits.

A killed or interrupted run resumes where it stopped (same command, same --output_dir). Results:
<output_dir>/summary.md and <output_dir>/<policy>/{results.json,results.md,episodes.jsonl,plots/}. Exit codes:
0 done, 1 done but some episodes ended in an engine error (not scored; the same command retries them),
2 bad input or an engine that cannot be reached (one line on stderr), 130 interrupted (Ctrl-C).
See docs/EVAL.md; `python eval.py --help` lists every option.
"""

from __future__ import annotations

import sys

from openfly_agent.data.schema import SchemaError
from openfly_agent.eval.config import EvalConfig, EvalInputError
from openfly_agent.eval.run import run as evaluate
from openfly_agent.rollout.checkpoints import CheckpointError
from openfly_agent.utils.cli_help import command_help, wants_help
from openfly_agent.utils.cli_options import CommandLineError
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.distributed import close_process_group
from openfly_agent.utils.errors import RecordError, root_cause
from openfly_agent.utils.logging_utils import setup_logging

EXIT_EPISODE_ERRORS = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C

DESCRIPTION = (
    "Fly a policy (a checkpoint, or a baseline) through the test episodes of a dataset in a simulator and "
    "score every episode under the `openfly` and `standard` metric profiles (docs/EVAL.md). Relative paths are "
    "relative to the working directory."
)
EXAMPLES = (
    "python eval.py --checkpoint=outputs/train/tiny/checkpoints/last --split=[test_seen,test_unseen] "
    "--sim.type=embedded",
    "python eval.py --policy=oracle --baselines=[random,stop,forward] --dataset_root=outputs/datasets/embedded-small",
    "python eval.py --config_path=configs/eval/embedded.yaml --checkpoint=<folder or Hub id>",
    "accelerate launch eval.py ...        # episodes split over processes / GPUs, results merged by rank 0",
)


def help_text(argv: list[str]) -> str:
    """`--help`: every option with the value the same command line without `--help` would use."""
    placeholders = {"checkpoint": "<checkpoint>"}  # the agent refuses a config without one
    return command_help(EvalConfig, argv, "eval.py", DESCRIPTION, EXAMPLES, placeholders=placeholders)


def set_torch_threads(count: int | None) -> None:
    """The process's torch CPU threads (None: torch's default). Set here, by the command, not by the evaluation
    library: torch numerics depend on the count, so an in-process caller keeps its own."""
    if count is not None:
        import torch  # lazy: --help stays fast

        torch.set_num_threads(count)


def run(argv: list[str]) -> int:
    """Parse the command line, run the evaluation, print the comparison table (rank 0); the exit code."""
    from draccus.utils import ParsingError

    if wants_help(argv):
        print(help_text(argv), end="")
        return 0
    setup_logging()
    try:
        cfg = parse_config(EvalConfig, argv)
        set_torch_threads(cfg.torch_threads)
        outcome = evaluate(cfg)
    except (
        ParsingError,
        EvalInputError,
        FileNotFoundError,
        SchemaError,
        RecordError,
        CommandLineError,
        CheckpointError,
    ) as err:
        print(f"eval.py: {root_cause(err) if isinstance(err, ParsingError) else err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not outcome:  # ranks other than 0
        return 0
    print(outcome["summary_markdown"])
    print(f"Results, per-scene tables and plots: {outcome['output_dir']}/")
    errors = {name: n for name, n in outcome["errors"].items() if n}
    if errors:
        counts = ", ".join(f"{name}: {n}" for name, n in errors.items())
        print(
            f"eval.py: episodes ended in an engine error and were not scored ({counts}); see `error` in "
            "episodes.jsonl, then run the same command again to retry them",
            file=sys.stderr,
        )
        return EXIT_EPISODE_ERRORS
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (Ctrl-C: one line and 130, no traceback)."""
    try:
        code = run(list(sys.argv[1:] if argv is None else argv))
    except KeyboardInterrupt:
        print("eval.py: interrupted; run the same command again to resume", file=sys.stderr)
        code = EXIT_INTERRUPTED
    close_process_group(synchronize=code in (0, EXIT_EPISODE_ERRORS))
    return code


if __name__ == "__main__":
    sys.exit(main())

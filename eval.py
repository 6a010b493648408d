"""Closed-loop evaluation of a checkpoint (and baselines) on the test-seen / test-unseen splits.

    python eval.py --checkpoint runs/tiny/checkpoints/last --split test_seen test_unseen --sim embedded
    python eval.py --policy oracle --baselines random stop forward --dataset_root <dataset root>
    python eval.py --config_path configs/eval/embedded.yaml --checkpoint <folder or Hub id>
    accelerate launch eval.py ...        # episodes split over processes / GPUs, results merged by rank 0

A killed run resumes where it stopped (same --output_dir). Results: <output_dir>/summary.md and
<output_dir>/<policy>/{results.json,results.md,episodes.jsonl,plots/}. Exit codes: 0 done, 1 done but some
episodes ended in an engine error (not scored; the same command retries them), 2 bad input or an engine that
cannot be reached (one line on stderr). See docs/EVAL.md.
"""

from __future__ import annotations

import sys

from openfly_agent.eval.cli import normalize_argv
from openfly_agent.eval.config import EvalConfig
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import RecordError, root_cause
from openfly_agent.utils.logging_utils import setup_logging

EXIT_EPISODE_ERRORS = 1
EXIT_BAD_INPUT = 2


def run(argv: list[str]) -> int:
    """Parse the command line, run the evaluation, print the comparison table (rank 0); the exit code."""
    from draccus.utils import ParsingError

    from openfly_agent.data.schema import SchemaError
    from openfly_agent.eval.config import EvalInputError
    from openfly_agent.eval.run import run as evaluate

    setup_logging()
    try:
        cfg = parse_config(EvalConfig, normalize_argv(argv))
        outcome = evaluate(cfg)
    except (ParsingError, EvalInputError, FileNotFoundError, SchemaError, RecordError) as err:
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
    """Entry point; returns the exit code."""
    from openfly_agent.utils.distributed import close_process_group

    code = run(list(sys.argv[1:] if argv is None else argv))
    close_process_group(synchronize=code in (0, EXIT_EPISODE_ERRORS))
    return code


if __name__ == "__main__":
    sys.exit(main())

"""`python -m openfly_agent.recipe --config_path configs/recipe/main_job.yaml [--<field>=VALUE ...]`

Runs the navigation recipe (openfly_agent/recipe/run.py); run the same command again to resume. At the end it
prints, and writes to `<output_dir>/summary.md`, each training stage's steps against its budget (a stage its time
guard cut short says so) above the evaluation tables.
"""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path

import draccus

from openfly_agent.recipe.config import RecipeConfig
from openfly_agent.recipe.progress import recipe_report
from openfly_agent.recipe.run import run_recipe
from openfly_agent.utils.cli_help import command_help, wants_help
from openfly_agent.utils.cli_options import CommandLineError
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import root_cause
from openfly_agent.utils.logging_utils import setup_logging

PROG = "python -m openfly_agent.recipe"
DESCRIPTION = (
    "the navigation recipe as one resumable command: dataset -> grounding data -> grounding stage -> navigation "
    "stage -> DAgger rounds -> RL stage (rl.steps > 0) -> closed-loop evaluation with every baseline "
    "(docs/TRAINING.md, 'The recipe')"
)
EXAMPLES = (
    f"{PROG} --config_path configs/recipe/main_job.yaml          # the README's main job (~30 min on 2 cores)",
    f"{PROG} --config_path configs/recipe/tiny-recipe.yaml --output_dir outputs/recipe",
)
logger = logging.getLogger("openfly_agent.recipe")
EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process SIGTERM ended


class Terminated(Exception):
    """SIGTERM reached the recipe (a scheduler's preemption, `kill`): raised where the recipe waits on its stage,
    so that the stage's processes are stopped with it (openfly_agent/recipe/run.py) instead of running on."""


def _terminated(signum, _frame) -> None:
    raise Terminated(signal.Signals(signum).name)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if wants_help(args):
        sys.stdout.write(command_help(RecipeConfig, args, PROG, DESCRIPTION, EXAMPLES))
        return 0
    try:
        cfg = parse_config(RecipeConfig, args)
    except (CommandLineError, ValueError, draccus.utils.ParsingError) as err:
        sys.stderr.write(f"{PROG}: {root_cause(err)}\n")
        return 2
    setup_logging()
    # Python's default SIGTERM handler would exit here and leave the running stage going on
    previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        run_recipe(cfg)
    except RuntimeError as err:
        sys.stderr.write(f"{PROG}: {err}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write(f"{PROG}: interrupted; run the same command again to resume\n")
        return 130
    except Terminated:
        sys.stderr.write(
            f"{PROG}: terminated (SIGTERM), its stage stopped; run the same command again to resume\n"
        )
        return EXIT_TERMINATED
    finally:
        signal.signal(signal.SIGTERM, previous)
    report = recipe_report(cfg)
    summary = Path(cfg.output_dir) / "summary.md"
    summary.write_text(report)
    print(report)
    logger.info("recipe complete: %s (per-policy tables in %s/eval*/)", summary, cfg.output_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Logging set-up, called by entry points only (never at import time)."""

from __future__ import annotations

import logging
import os

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# libraries whose INFO lines are chatter: accelerate says six of them per checkpoint saved or loaded (state,
# weights, optimizer, scheduler, sampler, RNG); the run's own line names the checkpoint. Their warnings stay.
QUIET_LIBRARIES = ("accelerate",)


def setup_logging(level: str | int | None = None) -> None:
    """Configure the root logger once for a command-line entry point.

    Under a launcher (`RANK` set, as accelerate and torchrun do) only rank 0 logs INFO: every process runs the
    same steps, so the other ranks' INFO lines would repeat rank 0's; they still log warnings and errors. The
    `QUIET_LIBRARIES` log their warnings and errors only, unless the level asked is DEBUG.
    """
    level = level or os.environ.get("OPENFLY_LOG_LEVEL", "INFO")
    if os.environ.get("RANK", "0") != "0":
        level = max(logging.getLevelName(level) if isinstance(level, str) else level, logging.WARNING)
    logging.basicConfig(level=level, format=LOG_FORMAT, datefmt="%H:%M:%S")
    numeric = logging.getLevelName(level) if isinstance(level, str) else level
    quiet = numeric if numeric <= logging.DEBUG else max(numeric, logging.WARNING)
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(quiet)

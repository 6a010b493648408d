"""Logging set-up, called by entry points only (never at import time)."""

from __future__ import annotations

import logging
import os

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def setup_logging(level: str | int | None = None) -> None:
    """Configure the root logger once for a command-line entry point.

    Under a launcher (`RANK` set, as accelerate and torchrun do) only rank 0 logs INFO: every process runs the
    same steps, so the other ranks' INFO lines would repeat rank 0's; they still log warnings and errors.
    """
    level = level or os.environ.get("OPENFLY_LOG_LEVEL", "INFO")
    if os.environ.get("RANK", "0") != "0":
        level = max(logging.getLevelName(level) if isinstance(level, str) else level, logging.WARNING)
    logging.basicConfig(level=level, format=LOG_FORMAT, datefmt="%H:%M:%S")

"""Logging set-up, called by entry points only (never at import time)."""

from __future__ import annotations

import logging
import os

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def setup_logging(level: str | int | None = None) -> None:
    """Configure the root logger once for a command-line entry point."""
    level = level or os.environ.get("OPENFLY_LOG_LEVEL", "INFO")
    logging.basicConfig(level=level, format=LOG_FORMAT, datefmt="%H:%M:%S")

"""The entry points' logging: accelerate's INFO chatter (six lines per checkpoint) is off, warnings stay."""

from __future__ import annotations

import logging

import pytest

from openfly_agent.utils.logging_utils import setup_logging


@pytest.fixture
def accelerate_logger():
    logger = logging.getLogger("accelerate")
    level = logger.level
    yield logger
    logger.setLevel(level)


def test_accelerate_logs_warnings_only_unless_debug_is_asked(accelerate_logger, monkeypatch):
    monkeypatch.delenv("RANK", raising=False)
    setup_logging("INFO")
    checkpointing = logging.getLogger("accelerate.checkpointing")  # "Model weights saved in ..." and the like
    assert not checkpointing.isEnabledFor(logging.INFO) and checkpointing.isEnabledFor(logging.WARNING)
    setup_logging("DEBUG")
    assert checkpointing.isEnabledFor(logging.DEBUG)

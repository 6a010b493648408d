"""Shared pytest set-up: offline Hub, deterministic seeds, the OpenFly fixtures folder (tests/fixtures/openfly)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Any accidental Hub call would stall ~47 s before failing (docs/INSTALL.md); tests never touch the network.
for _var in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

REPO_ROOT = Path(__file__).resolve().parents[1]
OPENFLY_FIXTURES = REPO_ROOT / "tests" / "fixtures" / "openfly"  # files of the official repository (MIT)


@pytest.fixture(scope="session")
def openfly_fixtures() -> Path:
    """The real OpenFly files (annotation JSON, landmark lists, scene configs), vendored in tests/fixtures/openfly."""
    return OPENFLY_FIXTURES


@pytest.fixture(autouse=True)
def _seed():
    import random

    import numpy as np

    random.seed(0)
    np.random.seed(0)
    try:
        import torch

        torch.manual_seed(0)
    except ImportError:
        pass
    yield


@pytest.fixture(autouse=True)
def _torch_threads():
    """Each test leaves torch's thread count as it found it. An entry point run in-process (eval.py's `main`
    sets `--torch_threads`, 1 by default) would otherwise leave its count to the tests after it, whose in-process
    training then no longer matches a fresh process bit for bit (setting the same count again changes nothing)."""
    import torch

    count = torch.get_num_threads()
    yield
    if torch.get_num_threads() != count:
        torch.set_num_threads(count)

"""Shared pytest set-up: offline Hub, deterministic seeds, the OpenFly fixtures folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Any accidental Hub call would stall ~47 s before failing (docs/INSTALL.md); tests never touch the network.
for _var in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

REPO_ROOT = Path(__file__).resolve().parents[1]


def _find_openfly_fixtures() -> Path | None:
    env = os.environ.get("OPENFLY_FIXTURES")
    candidates = [Path(env)] if env else []
    candidates += [
        REPO_ROOT / "shared" / "fixtures" / "openfly",
        REPO_ROOT.parent / "shared" / "fixtures" / "openfly",
    ]
    for path in candidates:
        if (path / "eval_test.json").is_file():
            return path
    return None


@pytest.fixture(scope="session")
def openfly_fixtures() -> Path:
    """The real OpenFly files (annotation JSON, landmark lists, scene configs) beside the checkout."""
    path = _find_openfly_fixtures()
    if path is None:
        pytest.fail("OpenFly fixtures not found: expected ../shared/fixtures/openfly or $OPENFLY_FIXTURES")
    return path


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

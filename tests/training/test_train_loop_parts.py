"""The training loop in parts (set-up, one step, after a step, finish): what happens after a step, decided
without a run, the test-only stop kept out of the user config, and no function of training/ over a screen."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from openfly_agent.training.after_step import Due, due, stop_reason
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.preflight import PreflightError
from openfly_agent.training.stops import (
    DONE,
    SIGNAL,
    STOP_AFTER_STEPS_ENV,
    TEST_STOP,
    TIME,
    forced_stop_step,
)
from openfly_agent.utils.config import config_to_dict

TRAINING = Path(__file__).resolve().parents[2] / "openfly_agent" / "training"
MAX_FUNCTION_LINES = 60  # one screen


# step, total steps, log / validation / save intervals -> (log, validate, save)
DUE_CASES = [
    (10, 100, 10, 200, 500, (True, False, False)),  # a log step only
    (7, 100, 10, 200, 500, (False, False, False)),  # nothing
    (100, 100, 10, 200, 500, (True, False, False)),  # the last step logs; 100 is no multiple of 200 nor 500
    (
        33,
        33,
        10,
        0,
        0,
        (True, False, False),
    ),  # the last step logs though 33 % 10 = 3; 0: never validate / save
    (200, 1000, 10, 200, 500, (True, True, False)),
    (500, 1000, 7, 250, 500, (False, True, True)),  # 500 = 71 x 7 + 3: no log
    (1000, 1000, 10, 200, 500, (True, True, True)),
    (3, 4, 1, 0, 2, (True, False, False)),
    (4, 4, 1, 0, 2, (True, False, True)),
]


@pytest.mark.parametrize("step, total, log, val, save, expected", DUE_CASES)
def test_due_says_what_a_step_does(step, total, log, val, save, expected):
    assert due(step, total, log, val, save) == Due(*expected)


class FakeStops:
    """Stop flags that answer `answer` and count how often they are asked (each ask is an all-reduce)."""

    def __init__(self, answer: str | None) -> None:
        self.answer, self.asked = answer, 0

    def reason(self) -> str | None:
        self.asked += 1
        return self.answer


# step, total steps, test-only stop step, what the stop flags say -> reason, whether the flags were asked
STOP_CASES = [
    (3, 10, None, None, None, True),  # go on
    (3, 10, None, TIME, TIME, True),
    (3, 10, None, SIGNAL, SIGNAL, True),
    (10, 10, None, SIGNAL, DONE, False),  # the last step: done, the flags are not asked
    (12, 10, None, None, DONE, False),  # past it (a resume with fewer steps configured)
    (3, 10, 3, SIGNAL, TEST_STOP, False),  # the test-only stop wins, without asking
    (10, 10, 3, None, TEST_STOP, False),
    (2, 10, 3, TIME, TIME, True),  # before the test-only stop
]


@pytest.mark.parametrize("step, total, stop_after, flags, expected, asked", STOP_CASES)
def test_stop_reason(step, total, stop_after, flags, expected, asked):
    stops = FakeStops(flags)
    assert stop_reason(step, total, stop_after, stops) == expected
    assert stops.asked == int(asked)


def test_the_test_only_stop_is_no_user_setting(monkeypatch):
    assert "stop_after_steps" not in config_to_dict(TrainConfig())
    monkeypatch.delenv(STOP_AFTER_STEPS_ENV, raising=False)
    assert forced_stop_step() is None
    monkeypatch.setenv(STOP_AFTER_STEPS_ENV, "3")
    assert forced_stop_step() == 3
    for bad in ("0", "-1", "three"):
        monkeypatch.setenv(STOP_AFTER_STEPS_ENV, bad)
        with pytest.raises(PreflightError, match=f"{STOP_AFTER_STEPS_ENV}='{bad}': use a step >= 1"):
            forced_stop_step()


def long_functions(folder: Path, limit: int) -> list[str]:
    """`file:line name (n lines)` of each function (methods and nested ones too) longer than `limit` lines."""
    found = []
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > limit:
                    found.append(f"{path.name}:{node.lineno} {node.name} ({length} lines)")
    return found


def test_the_length_check_finds_a_long_function(tmp_path):
    body = "\n".join(f"        x{i} = {i}" for i in range(60))
    (tmp_path / "long.py").write_text(
        f"def short():\n    return 1\n\n\nclass A:\n    def long(self):\n{body}\n"
    )
    assert long_functions(tmp_path, MAX_FUNCTION_LINES) == ["long.py:6 long (61 lines)"]


def test_no_function_of_training_is_longer_than_a_screen():
    assert long_functions(TRAINING, MAX_FUNCTION_LINES) == []

"""Why a run's loop ends: its last step, the time limit or a preemption signal (agreed on by every process), or
the test-only stop of `OPENFLY_STOP_AFTER_STEPS`."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from typing import Any

import torch
from accelerate import Accelerator

from openfly_agent.training.preflight import PreflightError

logger = logging.getLogger(__name__)
# the clock of the time limit (a module attribute: a test flies a run on a clock it advances itself)
monotonic_clock = time.monotonic

STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)  # cluster preemption notices (SLURM `--signal`)

# Why the loop ended (training/after_step.py): the configured steps are done, the time limit, a stop signal, or
# the test-only stop below (no final save).
DONE, TIME, SIGNAL, TEST_STOP = "done", "time", "signal", "test stop"
# Tests and device checks only, never a user setting: exit after this optimizer step WITHOUT the final save, as a
# crash would (the resume tests; bench/gpu_check.py's first step of a full fine-tune, whose checkpoint is ~90 GB).
STOP_AFTER_STEPS_ENV = "OPENFLY_STOP_AFTER_STEPS"


def forced_stop_step() -> int | None:
    """The step of the test-only stop (`OPENFLY_STOP_AFTER_STEPS`), None when the variable is unset or empty."""
    value = os.environ.get(STOP_AFTER_STEPS_ENV, "")
    if not value:
        return None
    if not value.isdigit() or int(value) < 1:
        raise PreflightError(f"{STOP_AFTER_STEPS_ENV}={value!r}: use a step >= 1, or unset it")
    return int(value)


class StopFlags:
    """Stop conditions every process agrees on: the time limit or a stop signal, on any process.

    SIGTERM / SIGUSR1 do not kill the run: the loop finishes the current optimizer step, saves a checkpoint and
    returns (without the final evaluation), so `--resume` continues from exactly there. Use as a context
    manager: the handlers are installed on entry (main thread only) and the previous ones restored on exit.

    Args:
    The time limit counts training time over the run's resumes: `elapsed_before_s` (saved in the checkpoint)
    plus the wall time since construction. `used_fraction` is the part of the limit used as of the last
    `reason()`, the value of rank 0 on every process (the lr schedule of a time horizon reads it).

    Args:
        accelerator: the run's Accelerator (the flags are all-reduced across its processes).
        time_limit_minutes: training time after which the run stops (None: no limit).
        elapsed_before_s: training seconds of the run before this process started (a resumed run).
    """

    def __init__(
        self, accelerator: Accelerator, time_limit_minutes: float | None, elapsed_before_s: float = 0.0
    ) -> None:
        self.accelerator = accelerator
        self.limit_s = None if time_limit_minutes is None else 60.0 * time_limit_minutes
        self.elapsed_before_s = elapsed_before_s
        self.started = monotonic_clock()
        self.used_fraction = 0.0 if self.limit_s is None else min(elapsed_before_s / self.limit_s, 1.0)
        self.signal_name: str | None = None
        self._signal_said = False
        self.stage = "training"  # what a stop signal ends: "training", or "the final evaluation"
        self._previous: dict[int, Any] = {}

    def elapsed_s(self) -> float:
        """Training seconds of the run so far (this process's clock), resumes included."""
        return self.elapsed_before_s + monotonic_clock() - self.started

    def __enter__(self) -> StopFlags:
        if threading.current_thread() is threading.main_thread():  # signal handlers live in the main thread
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc_info) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _on_signal(self, signum: int, frame) -> None:
        """Only records the signal: `reason` says so in the log. A handler that logged could interrupt the
        logging of a record in flight, whose line would then be lost."""
        self.signal_name = signal.Signals(signum).name

    def _say_signal(self) -> None:
        """The log line of a received signal, once, from the loop that acts on it."""
        if self.signal_name is None or self._signal_said:
            return
        self._signal_said = True
        if self.stage == "training":
            logger.warning(
                "%s received: stopping after this optimizer step and saving a checkpoint", self.signal_name
            )
        else:
            logger.warning("%s received: stopping %s (the checkpoint is saved)", self.signal_name, self.stage)

    def reason(self) -> str | None:
        """SIGNAL or TIME when any process must stop now, else None (one all-reduce per call)."""
        self._say_signal()
        elapsed = self.elapsed_s()
        if self.accelerator.num_processes == 1:  # nothing to agree on: no tensor, no device sync per step
            signalled = self.signal_name is not None
        else:  # rank 0's clock for everyone; a signal on any process counts
            main_elapsed = elapsed if self.accelerator.is_main_process else 0.0
            flags = torch.tensor(
                [float(self.signal_name is not None), main_elapsed],
                dtype=torch.float64,
                device=self.accelerator.device,
            )
            signal_count, elapsed = self.accelerator.reduce(flags, reduction="sum").tolist()
            signalled = signal_count > 0
        if self.limit_s is not None:
            self.used_fraction = min(elapsed / self.limit_s, 1.0)
        time_up = self.limit_s is not None and elapsed >= self.limit_s
        return SIGNAL if signalled else TIME if time_up else None

"""When a run stops before its last step: the time limit or a preemption signal, agreed on by every process."""

from __future__ import annotations

import logging
import signal
import threading
import time
from typing import Any

import torch
from accelerate import Accelerator

logger = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)  # cluster preemption notices (SLURM `--signal`)


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
        self.started = time.monotonic()
        self.used_fraction = 0.0 if self.limit_s is None else min(elapsed_before_s / self.limit_s, 1.0)
        self.signal_name: str | None = None
        self._signal_said = False
        self.stage = "training"  # what a stop signal ends: "training", or "the final evaluation"
        self._previous: dict[int, Any] = {}

    def elapsed_s(self) -> float:
        """Training seconds of the run so far (this process's clock), resumes included."""
        return self.elapsed_before_s + time.monotonic() - self.started

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
        """'signal' or 'time' when any process must stop now, else None (one all-reduce per call)."""
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
        return "signal" if signalled else "time" if time_up else None

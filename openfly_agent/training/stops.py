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
        accelerator: the run's Accelerator (the flags are all-reduced across its processes).
        time_limit_minutes: wall time after which the run stops (None: no limit), counted from construction.
    """

    def __init__(self, accelerator: Accelerator, time_limit_minutes: float | None) -> None:
        self.accelerator = accelerator
        self.deadline = None if time_limit_minutes is None else time.monotonic() + 60.0 * time_limit_minutes
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

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
        self.signal_name = signal.Signals(signum).name
        logger.warning(
            "%s received: stopping after this optimizer step and saving a checkpoint", self.signal_name
        )

    def reason(self) -> str | None:
        """'signal' or 'time' when any process must stop now, else None (one all-reduce per call)."""
        time_up = self.deadline is not None and time.monotonic() >= self.deadline
        if self.accelerator.num_processes == 1:  # nothing to agree on: no tensor, no device sync per step
            return "signal" if self.signal_name is not None else "time" if time_up else None
        flags = torch.tensor(
            [float(self.signal_name is not None), float(time_up)], device=self.accelerator.device
        )
        signalled, timed_out = (self.accelerator.reduce(flags, reduction="sum") > 0).tolist()
        return "signal" if signalled else "time" if timed_out else None

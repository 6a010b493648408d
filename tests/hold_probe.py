"""Run a script (train.py, eval.py) as `__main__`, held at a known point until a signal ends the hold.

    python tests/hold_probe.py final-eval train.py ...     # the final evaluation, before its first batch,
                                                           # until a stop signal (SIGTERM / SIGUSR1) is received
    python tests/hold_probe.py episodes:2 eval.py ...      # after the 2nd episode record is written, until a
                                                           # signal ends the process (SIGKILL, SIGINT)

When the hold starts it prints `hold-probe: holding` on stderr (one write). A test that waits for that line and
then signals the process knows where the signal lands, however slow the machine: the process cannot run past
the point (finish its evaluation, write its last episode) before the signal, as it could when a test signalled
on a line printed just before that point.
"""

from __future__ import annotations

import os
import runpy
import sys
import time

HOLDING = "hold-probe: holding"
HOLD_LIMIT_S = 300.0  # a hold no signal ends goes on after this (a broken test fails instead of hanging)


def _say_holding() -> None:
    sys.stderr.flush()
    os.write(sys.stderr.fileno(), f"{HOLDING}\n".encode())


def _hold(released=lambda: False) -> None:
    """Wait until `released()` or the signal's handler raises (KeyboardInterrupt) or the process is killed."""
    _say_holding()
    deadline = time.monotonic() + HOLD_LIMIT_S
    while not released() and time.monotonic() < deadline:
        time.sleep(0.02)


def hold_final_evaluation() -> None:
    """Hold the evaluation pass that can be stopped (the final one) before its first batch until `stop()`."""
    from openfly_agent.training import evaluate

    accumulate = evaluate._accumulate

    def held(model, loader, accelerator, bar, stop):
        if stop is not None:
            _hold(stop)
        return accumulate(model, loader, accelerator, bar, stop)

    evaluate._accumulate = held


def hold_after_episodes(count: int) -> None:
    """Hold once `count` episode records have been written (every policy's logs together, in order)."""
    from openfly_agent.eval.records import EpisodeLog

    append, written = EpisodeLog.append, []

    def held(self, record) -> None:
        append(self, record)
        written.append(record)
        if len(written) == count:
            _hold()

    EpisodeLog.append = held


if __name__ == "__main__":
    where, script = sys.argv[1], sys.argv[2]
    if where == "final-eval":
        hold_final_evaluation()
    elif where.startswith("episodes:"):
        hold_after_episodes(int(where.split(":", 1)[1]))
    else:
        raise SystemExit(f"hold_probe.py: unknown hold {where!r}")
    sys.argv = sys.argv[2:]
    runpy.run_path(script, run_name="__main__")

"""What happens after each optimizer step: the log line, a validation pass, a checkpoint, and whether to stop.

`due` (which of log / validate / save this step does) and `stop_reason` (why the loop ends here, if it does)
are the decisions, with no side effects; `after_step(run)` acts on them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from openfly_agent.training.evaluate import evaluate
from openfly_agent.training.metrics import memory_stats
from openfly_agent.training.run_setup import Run
from openfly_agent.training.saving import save_checkpoint
from openfly_agent.training.step_timer import log_line
from openfly_agent.training.stops import DONE, SIGNAL, TEST_STOP, TIME

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Due:
    """What the optimizer step just done does before the next one."""

    log: bool  # the train metrics: every `logging.log_interval` steps and at the last step
    validate: bool  # a pass on `data.val_split`: every `validation.interval` steps (0: never)
    save: bool  # a periodic checkpoint: every `checkpoint.save_interval` steps (0: never; a new best also saves)


def due(step: int, total_steps: int, log_interval: int, val_interval: int, save_interval: int) -> Due:
    """Which of log / validate / save step `step` of `total_steps` does, for the configured intervals."""
    return Due(
        log=step % log_interval == 0 or step == total_steps,
        validate=bool(val_interval) and step % val_interval == 0,
        save=bool(save_interval) and step % save_interval == 0,
    )


def stop_reason(step: int, total_steps: int, stop_after: int | None, stops) -> str | None:
    """Why the loop ends after step `step`, or None to go on.

    TEST_STOP at the test-only step `stop_after`; DONE at the last step (the stop flags are not asked: no
    all-reduce); else what `stops.reason()` says (TIME or SIGNAL, agreed on by every process, or None).
    """
    if stop_after is not None and step >= stop_after:
        return TEST_STOP
    if step >= total_steps:
        return DONE
    return stops.reason()


def after_step(run: Run) -> str | None:
    """Log, validate and save as `due` says for the step just done; return `stop_reason` (None: go on)."""
    cfg, step = run.cfg, run.state.step
    todo = due(
        step,
        run.opt.total_steps,
        cfg.logging.log_interval,
        cfg.validation.interval,
        cfg.checkpoint.save_interval,
    )
    if todo.log:
        _log_train(run)
    new_best = todo.validate and _validate(run)  # this pass beats the best so far (checkpoint.keep_best)
    if todo.save or new_best:
        save(run, new_best)
    reason = stop_reason(step, run.opt.total_steps, run.stop_after, run.stops)
    if run.opt.clock is not None:
        run.opt.clock.fraction = run.stops.used_fraction  # read by the next scheduler.step()
    if reason == TEST_STOP:
        logger.warning("stop step %d reached: exiting without the final save", step)
    elif reason in (TIME, SIGNAL):
        logger.info("stopping at step %d (%s)", step, reason)
    return reason


def save(run: Run, new_best: bool = False) -> None:
    """A checkpoint of the current step (every process); with `new_best`, it becomes `checkpoints/best`."""
    run.state.train_seconds = int(run.stops.elapsed_s())
    run.last_checkpoint = save_checkpoint(
        run.accelerator,
        run.opt.model,
        run.state,
        run.checkpoints,
        run.cfg,
        run.opt.ema,
        run.best if new_best else None,
    )
    run.saved_step = run.state.step


def _log_train(run: Run) -> None:
    """The train metrics since the last log to the trackers, one line to the log and the progress bar."""
    accelerator, state = run.accelerator, run.state
    train_logs = {**run.means.pop(accelerator), **run.meter.report(accelerator)}
    train_logs.update(memory_stats(accelerator.device), lr=float(run.opt.scheduler.get_last_lr()[0]))
    train_logs["epoch"] = state.epoch + state.step_in_epoch / run.opt.steps_per_epoch
    times = run.timer.report(accelerator)  # time/*, throughput/*: the log line below
    log_metrics(accelerator, "train", train_logs, state.step, times)
    if accelerator.is_main_process:
        logger.info(log_line(state.step, times, train_logs["tokens_per_s"]))
    run.progress.set_postfix(progress_postfix(train_logs))


def _validate(run: Run) -> bool:
    """A validation pass, logged; whether it is the best so far (always False without `checkpoint.keep_best`)."""
    figures = evaluate(run.opt.evaluated, run.val_loader, run.accelerator)
    log_metrics(run.accelerator, "val", figures, run.state.step)
    return run.best is not None and run.best.offer(figures, run.state.step)


def progress_postfix(train_logs: dict[str, float]) -> dict[str, str]:
    """The progress bar's `loss` and `acc`, each only when the step logged it (the grounding stage has no
    action accuracy: no `acc=nan`)."""
    shown = {"loss": ("loss", ".4f"), "acc": ("action_accuracy", ".3f")}
    return {
        name: format(train_logs[key], spec)
        for name, (key, spec) in shown.items()
        if key in train_logs and not math.isnan(train_logs[key])
    }


def log_metrics(
    accelerator, prefix: str, metrics: dict[str, float], step: int, named: dict[str, float] | None = None
) -> None:
    """Send `prefix/<name>` values (and the `named` ones under their own names, in the same record) to the
    trackers; validation and test figures also go to the log."""
    accelerator.log({**{f"{prefix}/{k}": v for k, v in metrics.items()}, **(named or {})}, step=step)
    if prefix != "train":
        logger.info(
            "step %d %s: %s", step, prefix, ", ".join(f"{k}={v:.4g}" for k, v in sorted(metrics.items()))
        )

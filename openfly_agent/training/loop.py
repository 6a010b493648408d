"""The training loop: accumulation, clipping, logging, periodic validation and checkpoints, stops."""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from tqdm.auto import tqdm

from openfly_agent import constants as C
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.evaluate import evaluate
from openfly_agent.training.metrics import RunningMeans, ThroughputMeter, count_llm_tokens, memory_stats
from openfly_agent.training.sampler import EpochShuffleSampler
from openfly_agent.training.saving import save_checkpoint
from openfly_agent.training.state import TrainerState

logger = logging.getLogger(__name__)


@dataclass
class TrainingRun:
    """Everything `fit` needs, built by `training.builder.build_run` (or by a test).

    Attributes:
        cfg: the run's configuration.
        accelerator: the run's Accelerator (trackers started, accumulation steps set).
        model: the prepared model; `model(batch) -> (loss, logs)`.
        optimizer: the prepared optimizer.
        scheduler: the prepared lr scheduler, stepped once per optimizer step.
        train_loader: the prepared training DataLoader over `sampler`.
        sampler: the epoch sampler inside `train_loader`.
        val_loader: held-out batches for periodic validation (None: no validation).
        test_loader: batches of the final evaluation split (None: skip it).
        state: counters; loaded from the checkpoint when resuming.
        total_steps: optimizer steps of the whole run.
        checkpoints: the checkpoint folder manager.
        export: writes the Hugging Face folder of the model into a checkpoint folder
            (`export(folder)`, called on every process; see `training/saving.py`).
        majority_rate: `() -> rate` of the most frequent train action on the final split (None: not reported).
        after_training: `(run) -> None` run on every process after the final checkpoint (the LoRA merge).
    """

    cfg: TrainConfig
    accelerator: Accelerator
    model: torch.nn.Module
    optimizer: Any
    scheduler: Any
    train_loader: Any
    sampler: EpochShuffleSampler
    val_loader: Any
    test_loader: Any
    state: TrainerState
    total_steps: int
    checkpoints: CheckpointManager
    export: Any
    majority_rate: Any = None
    after_training: Any = None


@dataclass
class FitResult:
    """What a run ends with: its counters, its last checkpoint and the final evaluation (if any)."""

    state: TrainerState
    checkpoint: Path | None
    final_metrics: dict[str, float]
    stopped_early: bool


STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)  # cluster preemption notices (SLURM `--signal`)


class _StopFlags:
    """Stop conditions every process agrees on: the time limit or a stop signal, on any process.

    SIGTERM / SIGUSR1 do not kill the run: the loop finishes the current optimizer step, saves a checkpoint and
    returns (without the final evaluation), so `--resume` continues from exactly there.
    """

    def __init__(self, cfg: TrainConfig, accelerator: Accelerator) -> None:
        self.accelerator = accelerator
        self.deadline = None
        if cfg.time_limit_minutes is not None:
            self.deadline = time.monotonic() + 60.0 * cfg.time_limit_minutes
        self.stop_after = cfg.stop_after_steps
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        """Catch the stop signals (main thread only; a no-op elsewhere, e.g. in a notebook worker thread)."""
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in STOP_SIGNALS:
            self._previous[sig] = signal.signal(sig, self._on_signal)

    def restore(self) -> None:
        """Put back the handlers that were there before `install`."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _on_signal(self, signum: int, frame) -> None:
        self.signal_name = signal.Signals(signum).name
        logger.warning(
            "%s received: stopping after this optimizer step and saving a checkpoint", self.signal_name
        )

    def stop_reason(self) -> str | None:
        """'signal' or 'time' when any process must stop now, else None (one all-reduce per call)."""
        time_up = self.deadline is not None and time.monotonic() >= self.deadline
        if self.accelerator.num_processes == 1:  # nothing to agree on: no tensor, no device sync per step
            return "signal" if self.signal_name is not None else "time" if time_up else None
        flags = torch.tensor(
            [float(self.signal_name is not None), float(time_up)], device=self.accelerator.device
        )
        signalled, timed_out = (self.accelerator.reduce(flags, reduction="sum") > 0).tolist()
        return "signal" if signalled else "time" if timed_out else None


def fit(run: TrainingRun) -> FitResult:
    """Train until `run.total_steps` (or the time limit), then save, evaluate and return.

    Each optimizer step consumes one global batch: `accumulation_steps` micro-batches on each process.
    Checkpoints are written every `checkpoint.save_interval` steps and at the end; `stop_after_steps` ends the
    process without the final save (how tests simulate a crash). SIGTERM / SIGUSR1 end the run after the current
    step with a checkpoint and no final evaluation.
    """
    flags = _StopFlags(run.cfg, run.accelerator)
    flags.install()
    acc = run.accelerator
    progress = tqdm(
        total=run.total_steps, initial=run.state.step, disable=not acc.is_main_process, desc="train"
    )
    try:
        return _fit(run, flags, progress)
    finally:
        progress.close()  # also on an error, so its message starts on a line of its own
        flags.restore()
        finish_trackers(acc)


def finish_trackers(accelerator: Accelerator) -> None:
    """Close the trackers (flush TensorBoard / W&B), on every way out of `fit`.

    Not `accelerator.end_training()`: that also destroys the process group while the prepared model is alive,
    which leaves DDP's Reducer as the group's last holder and can deadlock the rank at exit. The entry point
    closes the group once the run is released (`utils.distributed.close_process_group`).
    """
    for tracker in accelerator.trackers:
        tracker.finish()


def _fit(run: TrainingRun, flags: _StopFlags, progress: tqdm) -> FitResult:
    cfg, acc, state = run.cfg, run.accelerator, run.state
    means, meter = RunningMeans(), ThroughputMeter()
    run.model.train()
    stopped_early, reason = False, None
    last_checkpoint, saved_step = None, None
    while state.step < run.total_steps and not stopped_early:
        for batch in _epoch_batches(run):
            step_done = _train_micro_batch(run, batch, means)
            meter.update(int(batch[C.INPUT_IDS].shape[0]), count_llm_tokens(batch, cfg.model))
            if not step_done:
                continue
            _finish_step(run)
            progress.update(1)
            if state.step % cfg.logging.log_interval == 0 or state.step == run.total_steps:
                _log_train(run, means, meter, progress)
            if cfg.validation.interval and state.step % cfg.validation.interval == 0 and run.val_loader:
                _log_metrics(run, "val", evaluate(run.model, run.val_loader, acc))
            if cfg.checkpoint.save_interval and state.step % cfg.checkpoint.save_interval == 0:
                last_checkpoint, saved_step = save_checkpoint(run), state.step
            if flags.stop_after is not None and state.step >= flags.stop_after:
                logger.warning(
                    "stop_after_steps=%d reached: exiting without the final save", flags.stop_after
                )
                progress.close()
                return FitResult(state, last_checkpoint, {}, stopped_early=True)
            if state.step >= run.total_steps:
                break
            reason = flags.stop_reason()
            if reason == "time":
                logger.info("time_limit_minutes=%s reached at step %d", cfg.time_limit_minutes, state.step)
            if reason is not None:
                stopped_early = True
                break
    progress.close()
    if saved_step != state.step:
        last_checkpoint = save_checkpoint(run)
    if reason == "signal":
        logger.warning(
            "stopped by a signal at step %d; `--resume` continues from %s", state.step, last_checkpoint
        )
        return FitResult(state, last_checkpoint, {}, stopped_early=True)
    if run.after_training is not None:
        run.after_training(run)
    final = _final_evaluation(run)
    return FitResult(state, last_checkpoint, final, stopped_early)


def _epoch_batches(run: TrainingRun):
    """The prepared train loader for `state.epoch`, skipping the micro-batches already consumed."""
    state, acc = run.state, run.accelerator
    run.train_loader.set_epoch(state.epoch)
    skip = state.step_in_epoch * acc.gradient_accumulation_steps
    if skip:
        logger.info(
            "resuming epoch %d after %d steps (%d micro-batches skipped)",
            state.epoch,
            state.step_in_epoch,
            skip,
        )
        return acc.skip_first_batches(run.train_loader, skip)
    return run.train_loader


def _train_micro_batch(run: TrainingRun, batch: dict, means: RunningMeans) -> bool:
    """Forward + backward of one micro-batch; steps the optimizer on the last one. True if it stepped."""
    acc, model = run.accelerator, run.model
    with acc.accumulate(model):
        loss, logs = model(batch)
        acc.backward(loss)
        if acc.sync_gradients and run.cfg.optim.max_grad_norm is not None:
            grad_norm = acc.clip_grad_norm_(model.parameters(), run.cfg.optim.max_grad_norm)
            if grad_norm is not None:  # DeepSpeed clips inside its engine and returns None
                logs = {**logs, "grad_norm": float(grad_norm)}
        run.optimizer.step()
        run.optimizer.zero_grad(set_to_none=True)
    means.add(logs)
    return acc.sync_gradients


def _finish_step(run: TrainingRun) -> None:
    """Advance the schedule and the counters after an optimizer step."""
    state = run.state
    run.scheduler.step()
    state.step += 1
    state.step_in_epoch += 1
    state.samples_seen += run.cfg.batch.global_batch_size
    state.world_size = run.accelerator.num_processes
    if state.step_in_epoch >= run.sampler.steps_per_epoch:
        state.epoch += 1
        state.step_in_epoch = 0


def _log_train(run: TrainingRun, means: RunningMeans, meter: ThroughputMeter, progress) -> None:
    """Average the interval's logs over processes and send them to the trackers."""
    acc = run.accelerator
    metrics = means.pop(acc)
    metrics.update(meter.report(acc))
    metrics.update(memory_stats(acc.device))
    metrics["lr"] = float(run.scheduler.get_last_lr()[0])
    metrics["epoch"] = run.state.epoch + run.state.step_in_epoch / run.sampler.steps_per_epoch
    _log_metrics(run, "train", metrics)
    if acc.is_main_process:
        progress.set_postfix(
            loss=f"{metrics.get('loss', float('nan')):.4f}",
            acc=f"{metrics.get('action_accuracy', float('nan')):.3f}",
        )


def _log_metrics(run: TrainingRun, prefix: str, metrics: dict[str, float]) -> None:
    run.accelerator.log({f"{prefix}/{k}": v for k, v in metrics.items()}, step=run.state.step)
    if prefix != "train":
        logger.info(
            "step %d %s: %s",
            run.state.step,
            prefix,
            ", ".join(f"{k}={v:.4g}" for k, v in sorted(metrics.items())),
        )


def _final_evaluation(run: TrainingRun) -> dict[str, float]:
    """Offline action accuracy / box IoU on the test split, next to the majority-class rate."""
    if run.test_loader is None:
        return {}
    metrics = evaluate(run.model, run.test_loader, run.accelerator)
    if run.majority_rate is not None:
        metrics["majority_class_rate"] = float(run.majority_rate())
    _log_metrics(run, "test", metrics)
    return metrics

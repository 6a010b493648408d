"""`train(cfg)`: one OpenFly-Agent training run, from the input checks to the final offline evaluation.

Readable top to bottom, as OpenVLA's `train(cfg)` and nanoGPT's loop: checks, data, agent and processor,
optimizer and loaders through accelerate, then the loop (accumulation, clipping, logging, validation on
`data.val_split`, checkpoints and the best one, stops), then the final checkpoint, the LoRA merge and the
test-split evaluation, the only time the test split is evaluated. The helpers it calls each do one thing
(training/builder.py, loaders.py, saving.py, evaluate.py, stops.py, ...).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.persistence.lora_checkpoint import merged_model_of
from openfly_agent.training.accelerator import closing_trackers, flat_config, make_accelerator
from openfly_agent.training.best import BestMetric
from openfly_agent.training.builder import load_splits, majority_class_rate, prepare_agent
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import STAGE_NAVIGATION, STAGE_RL, TrainConfig
from openfly_agent.training.ema import make_ema, update_ema
from openfly_agent.training.evaluate import evaluate, make_eval_loader
from openfly_agent.training.export import export_merged_lora
from openfly_agent.training.loaders import epoch_batches, make_train_loader
from openfly_agent.training.memory_estimate import check_memory
from openfly_agent.training.metrics import RunningMeans, ThroughputMeter, count_llm_tokens, memory_stats
from openfly_agent.training.optim import ScheduleClock, make_optimizer, make_scheduler
from openfly_agent.training.preflight import check_dataset_root, check_output_dir, resolve_val_split
from openfly_agent.training.resume_settings import record_run_settings, resume_changes
from openfly_agent.training.rl_trainer import train_rl
from openfly_agent.training.saving import register_state_hooks, restore_checkpoint, save_checkpoint
from openfly_agent.training.stages import stage_data
from openfly_agent.training.state import TrainerState
from openfly_agent.training.step_timer import StepTimer, log_line
from openfly_agent.training.stops import StopFlags
from openfly_agent.training.throughput import StepFlops, device_peak_flops
from openfly_agent.training.trackers import start_trackers
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a run ends with (on every process).

    Attributes:
        state: the counters at the end.
        checkpoint: the last checkpoint written (None when none was).
        final_metrics: the final evaluation of `data.test_split` (`{}` when skipped or stopped early).
        stopped_early: the time limit, a stop signal or `stop_after_steps` ended the run.
        agent: the trained agent (unwrapped from accelerate's wrappers).
        is_main_process: whether this process is rank 0.
    """

    state: TrainerState
    checkpoint: Path | None
    final_metrics: dict[str, float]
    stopped_early: bool
    agent: OpenFlyAgent
    is_main_process: bool


def train(cfg: TrainConfig) -> TrainResult:
    """Train the agent of `cfg` (docs/TRAINING.md) on every process of the launch; see the module docstring.

    Raises:
        PreflightError: bad input (output folder, dataset, batch sizes, checkpoints), before any compute.
    """
    if cfg.stage == STAGE_RL:  # its own loop: rollouts in the simulator, then policy updates
        run = train_rl(cfg)
        return TrainResult(run.state, run.checkpoint, {}, run.stopped_early, run.agent, run.is_main_process)
    # 1. Checks before any compute: each failure is a PreflightError that says what to change.
    resume_from = check_output_dir(cfg.output_dir, cfg.resume)
    # the dataset's val split; test_seen (with a warning) on a dataset without one, as the run records it
    data, val_warning = resolve_val_split(cfg.data)
    cfg = dataclasses.replace(cfg, data=data)
    # a resume refuses settings other than its checkpoint's, except RESUMABLE_KEYS (training/resume_settings.py)
    setting_changes = resume_changes(cfg, resume_from)
    check_dataset_root(cfg.data)
    accelerator = make_accelerator(cfg)  # processes, precision, accumulation = global / (per device x world)
    # CUDA: the per-GPU estimate; refused here when it cannot fit, before any read
    check_memory(cfg, accelerator)
    checkpoints = CheckpointManager(cfg.output_dir, cfg.checkpoint.keep_last)
    if accelerator.is_main_process:
        checkpoints.remove_stale_staging()
    splits = load_splits(cfg.data, cfg.model.grounding)
    if val_warning:
        logger.warning(val_warning)

    # 2. The agent, whose processor prepares every input, and the stage's samples of each split
    #    (navigation: per-step samples with history; grounding: expressions and instruction targets).
    agent = prepare_agent(cfg, splits, accelerator, resume_from)
    data = stage_data(cfg, splits, agent)
    train_set, val_set, test_set, collate = data.train, data.val, data.test, data.collate
    if accelerator.is_main_process:  # train_config.json keeps the first settings; resumes append changes
        record_run_settings(cfg, resume_from, setting_changes)

    # 3. Optimizer, schedule and loaders; accelerate wraps them for the launch (DDP / FSDP / DeepSpeed).
    train_loader, sampler = make_train_loader(train_set, collate, cfg)
    total_steps = cfg.steps or max(1, math.ceil(cfg.epochs * sampler.steps_per_epoch))
    optim = cfg.optim
    fused = optim.fused_adamw and accelerator.device.type == "cuda"  # the fused kernel: CUDA only
    optimizer = make_optimizer(agent, optim.lr, optim.weight_decay, optim.betas, optim.eps, fused=fused)
    step_flops = StepFlops.from_agent(agent)  # the log's model FLOPs: the unwrapped agent, as it trains
    clock = ScheduleClock() if optim.horizon == "time" else None  # the used part of the time budget
    scheduler = make_scheduler(
        optimizer, optim.schedule, optim.warmup_steps, total_steps, optim.min_lr_ratio, clock
    )
    model, optimizer, train_loader, scheduler = accelerator.prepare(agent, optimizer, train_loader, scheduler)
    register_state_hooks(accelerator)  # checkpoints keep trainable tensors only
    ema = make_ema(accelerator, model, optim.ema_decay)  # None: no weight average
    evaluated = model if ema is None else ema.module  # what validation, the test split and exports see
    eval_batch = cfg.validation.per_device_batch_size or cfg.batch.per_device_batch_size
    val_loader = test_loader = None
    test_indices: list[int] = []
    if cfg.validation.interval:
        val_loader, _ = make_eval_loader(
            val_set, cfg.validation.max_samples, eval_batch, accelerator, collate, cfg.data.num_workers
        )
    if cfg.validation.final_eval:
        test_loader, test_indices = make_eval_loader(
            test_set, cfg.validation.final_max_samples, eval_batch, accelerator, collate, cfg.data.num_workers
        )
    state = TrainerState(world_size=accelerator.num_processes)
    last_checkpoint, saved_step = None, None
    if resume_from is not None:
        state = restore_checkpoint(accelerator, resume_from, ema)  # optimizer, schedule, RNG, weights
        last_checkpoint, saved_step = resume_from, state.step  # that step is saved: not again at the end
        if state.step >= total_steps:
            logger.info(
                "nothing left to train: %s is at step %d of the %d configured; no checkpoint is written and its "
                "weights are left as they are",
                resume_from,
                state.step,
                total_steps,
            )
    # checkpoint.keep_best: the best validation figure so far (read back from `checkpoints/best` on a resume)
    keep_best = cfg.checkpoint.keep_best
    best = BestMetric.resume(keep_best, checkpoints.best()) if keep_best else None
    # a resume first drops what was logged after its checkpoint: those steps are logged again (trackers.py)
    start_trackers(
        accelerator, cfg.logging.project, flat_config(cfg), None if resume_from is None else state.step
    )
    logger.info(
        "run: %d steps (%d per epoch), starting at step %d", total_steps, sampler.steps_per_epoch, state.step
    )

    # 4. The loop: one optimizer step = one global batch = `accumulation` micro-batches on each process.
    means, meter = RunningMeans(), ThroughputMeter()
    timer = StepTimer(accelerator.device, step_flops, device_peak_flops(accelerator.device))  # the time split
    progress = progress_bar(
        total=total_steps, initial=state.step, disable=not accelerator.is_main_process, desc="train"
    )
    model.train()
    reason = None
    stops = StopFlags(accelerator, cfg.time_limit_minutes, elapsed_before_s=state.train_seconds)
    if clock is not None:
        clock.fraction = stops.used_fraction
    # The bar, the stop-signal handlers and the trackers are closed on every way out, an error included.
    with progress, stops, closing_trackers(accelerator):
        while state.step < total_steps and reason is None:
            for batch in timer.batches(epoch_batches(train_loader, train_set, state, accelerator)):
                with accelerator.accumulate(model):  # gradients sync on the last micro-batch of a step
                    loss, logs = model(batch)
                    timer.end("forward")
                    accelerator.backward(loss)
                    timer.end("backward")
                    if accelerator.sync_gradients and optim.max_grad_norm is not None:
                        grad_norm = accelerator.clip_grad_norm_(model.parameters(), optim.max_grad_norm)
                        if grad_norm is not None:  # DeepSpeed clips inside its engine and returns None
                            logs = {**logs, "grad_norm": float(grad_norm)}
                    optimizer.step()  # a no-op until the step's last micro-batch
                    optimizer.zero_grad(set_to_none=True)
                    timer.end("optimizer")
                timer.count(batch)
                means.add(logs)
                meter.update(int(batch[C.INPUT_IDS].shape[0]), count_llm_tokens(batch, cfg.model))
                if not accelerator.sync_gradients:
                    continue
                scheduler.step()
                timer.step_done()
                state.advance(cfg.batch.global_batch_size, sampler.steps_per_epoch, accelerator.num_processes)
                if ema is not None:
                    update_ema(ema, accelerator, model, state.step)
                progress.update(1)
                if state.step % cfg.logging.log_interval == 0 or state.step == total_steps:
                    train_logs = {**means.pop(accelerator), **meter.report(accelerator)}
                    train_logs.update(memory_stats(accelerator.device), lr=float(scheduler.get_last_lr()[0]))
                    train_logs["epoch"] = state.epoch + state.step_in_epoch / sampler.steps_per_epoch
                    times = timer.report(accelerator)  # time/*, throughput/*: the log line below
                    log_metrics(accelerator, "train", train_logs, state.step, times)
                    if accelerator.is_main_process:
                        logger.info(log_line(state.step, times, train_logs["tokens_per_s"]))
                    progress.set_postfix(progress_postfix(train_logs))
                new_best = False  # this step's validation pass beats the best so far (checkpoint.keep_best)
                if val_loader is not None and state.step % cfg.validation.interval == 0:
                    val_figures = evaluate(evaluated, val_loader, accelerator)
                    log_metrics(accelerator, "val", val_figures, state.step)
                    new_best = best is not None and best.offer(val_figures, state.step)
                periodic = cfg.checkpoint.save_interval and state.step % cfg.checkpoint.save_interval == 0
                if periodic or new_best:
                    state.train_seconds = int(stops.elapsed_s())
                    last_checkpoint = save_checkpoint(
                        accelerator, model, state, checkpoints, cfg, ema, best if new_best else None
                    )
                    saved_step = state.step
                if cfg.stop_after_steps is not None and state.step >= cfg.stop_after_steps:
                    logger.warning("stop_after_steps=%d reached: exiting without the final save", state.step)
                    progress.close()
                    return _result(state, last_checkpoint, {}, True, accelerator, evaluated)
                if state.step >= total_steps:
                    break
                reason = stops.reason()  # the time limit or SIGTERM / SIGUSR1 on any process
                if clock is not None:
                    clock.fraction = stops.used_fraction  # read by the next scheduler.step()
                if reason is not None:
                    logger.info("stopping at step %d (%s)", state.step, reason)
                    break
        progress.close()

        # 5. The end: a checkpoint of the last step, the LoRA merge, the offline evaluation of the test split.
        if saved_step != state.step:
            state.train_seconds = int(stops.elapsed_s())
            last_checkpoint = save_checkpoint(accelerator, model, state, checkpoints, cfg, ema)
        if reason == "signal":
            logger.warning(
                "stopped by a signal at step %d; `--resume` continues from %s", state.step, last_checkpoint
            )
            return _result(state, last_checkpoint, {}, True, accelerator, evaluated)
        if cfg.use_lora and cfg.lora.merge_at_end and not _merge_is_current(last_checkpoint):
            export_merged_lora(accelerator, evaluated, cfg.output_dir)  # full weights in <output_dir>/merged
        final: dict[str, float] = {}
        if test_loader is not None:
            stops.stage = "the final evaluation"
            logger.info("final evaluation on %s: %d samples", cfg.data.test_split, len(test_indices))
            final = evaluate(evaluated, test_loader, accelerator, "test", lambda: stops.reason() == "signal")
            if final is None:  # SIGTERM / SIGUSR1 during it: no figures, as a stop mid-training
                logger.warning(
                    "stopped by a signal during the final evaluation; nothing written as its result; `--resume` "
                    "evaluates %s",
                    last_checkpoint,
                )
                return _result(state, last_checkpoint, {}, True, accelerator, evaluated)
            if cfg.stage == STAGE_NAVIGATION:
                final["majority_class_rate"] = majority_class_rate(train_set, test_set, test_indices)
            log_metrics(accelerator, "test", final, state.step)
        return _result(state, last_checkpoint, final, reason is not None, accelerator, evaluated)


def _merge_is_current(checkpoint: Path | None) -> bool:
    """Whether `<output_dir>/merged` already holds the merge of `checkpoint` (a resume with nothing left to
    train after a finished run): then it is not written again."""
    return checkpoint is not None and merged_model_of(checkpoint) is not None


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


def _result(state, checkpoint, final, stopped_early, accelerator, model) -> TrainResult:
    return TrainResult(
        state, checkpoint, final, stopped_early, accelerator.unwrap_model(model), accelerator.is_main_process
    )

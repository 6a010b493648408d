"""`train(cfg)`: one OpenFly-Agent training run, from the input checks to the final offline evaluation.

Four parts, read as nanoGPT's loop: `set_up` (training/run_setup.py: checks, data, agent and processor,
optimizer and loaders through accelerate, a resumed state), `train_micro_batch` below (forward, backward and,
on a step's last micro-batch, clipping, the optimizer and schedule step, the counters and the weight average),
`after_step` (training/after_step.py: logging, validation on `data.val_split`, checkpoints and the best one, the
stop reason), and `finish` (training/finish.py: the final checkpoint, the LoRA merge and the test-split
evaluation, the only time the test split is evaluated).
"""

from __future__ import annotations

from openfly_agent import constants as C
from openfly_agent.training.accelerator import closing_trackers
from openfly_agent.training.after_step import after_step
from openfly_agent.training.config import STAGE_RL, TrainConfig
from openfly_agent.training.ema import update_ema
from openfly_agent.training.finish import TrainResult, finish
from openfly_agent.training.metrics import count_llm_tokens
from openfly_agent.training.rl_trainer import train_rl
from openfly_agent.training.run_setup import Run, set_up
from openfly_agent.training.stops import DONE


def train(cfg: TrainConfig) -> TrainResult:
    """Train the agent of `cfg` (docs/TRAINING.md) on every process of the launch; see the module docstring.

    Raises:
        PreflightError: bad input (output folder, dataset, batch sizes, checkpoints), before any compute.
    """
    if cfg.stage == STAGE_RL:  # its own loop: rollouts in the simulator, then policy updates
        rl = train_rl(cfg)
        return TrainResult(rl.state, rl.checkpoint, {}, rl.stopped_early, rl.agent, rl.is_main_process)
    run = set_up(cfg)
    reason = DONE if run.state.step >= run.opt.total_steps else None  # a resume with nothing left to train
    # The bar, the stop-signal handlers and the trackers are closed on every way out, an error included.
    with run.progress, run.stops, closing_trackers(run.accelerator):
        while reason is None:  # one pass of the inner loop: the rest of an epoch
            for batch in run.batches():
                if train_micro_batch(run, batch):  # an optimizer step ended
                    reason = after_step(run)  # log, validate, save; DONE, TIME, SIGNAL, TEST_STOP or None
                    if reason is not None:
                        break
        result = finish(run, reason)
    return result


def train_micro_batch(run: Run, batch: dict) -> bool:
    """One micro-batch; whether it ended an optimizer step (one global batch = `accumulation` micro-batches on
    each process), which also steps the schedule and the counters and updates the weight average."""
    accelerator, model, timer, optim = run.accelerator, run.opt.model, run.timer, run.cfg.optim
    with accelerator.accumulate(model):  # gradients sync on the last micro-batch of a step
        loss, logs = model(batch)
        timer.end("forward")
        accelerator.backward(loss)
        timer.end("backward")
        if accelerator.sync_gradients and optim.max_grad_norm is not None:
            grad_norm = accelerator.clip_grad_norm_(model.parameters(), optim.max_grad_norm)
            if grad_norm is not None:  # DeepSpeed clips inside its engine and returns None
                logs = {**logs, "grad_norm": float(grad_norm)}
        run.opt.optimizer.step()  # a no-op until the step's last micro-batch
        run.opt.optimizer.zero_grad(set_to_none=True)
        timer.end("optimizer")
    timer.count(batch)
    run.means.add(logs)
    run.meter.update(int(batch[C.INPUT_IDS].shape[0]), count_llm_tokens(batch, run.cfg.model))
    if not accelerator.sync_gradients:
        return False
    run.opt.scheduler.step()
    timer.step_done()
    run.state.advance(run.cfg.batch.global_batch_size, run.opt.steps_per_epoch, accelerator.num_processes)
    if run.opt.ema is not None:
        update_ema(run.opt.ema, accelerator, model, run.state.step)
    run.progress.update(1)
    return True

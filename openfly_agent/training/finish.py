"""The last part of a training run: `finish(run, reason)` after the loop ends.

A checkpoint of the last step (unless that step is saved already, or the test-only stop ended the run), then,
for a run that ended on its last step or its time limit, the LoRA merge and the offline evaluation of
`data.test_split`, the only time the test split is evaluated. A stop signal ends the run after its checkpoint.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.persistence.lora_checkpoint import merged_model_of
from openfly_agent.training.after_step import log_metrics, save
from openfly_agent.training.builder import majority_class_rate
from openfly_agent.training.config import STAGE_NAVIGATION
from openfly_agent.training.evaluate import evaluate
from openfly_agent.training.export import export_merged_lora
from openfly_agent.training.run_setup import Run
from openfly_agent.training.state import TrainerState
from openfly_agent.training.stops import DONE, SIGNAL, TEST_STOP, TIME

logger = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a run ends with (on every process).

    Attributes:
        state: the counters at the end.
        checkpoint: the last checkpoint written (None when none was).
        final_metrics: the final evaluation of `data.test_split` (`{}` when skipped or stopped early).
        stopped_early: the time limit, a stop signal or the test-only stop ended the run.
        agent: the trained agent (unwrapped from accelerate's wrappers).
        is_main_process: whether this process is rank 0.
    """

    state: TrainerState
    checkpoint: Path | None
    final_metrics: dict[str, float]
    stopped_early: bool
    agent: OpenFlyAgent
    is_main_process: bool


def finish(run: Run, reason: str) -> TrainResult:
    """End the run the loop left for `reason` (DONE, TIME, SIGNAL or TEST_STOP); see the module docstring."""
    run.progress.close()
    final: dict[str, float] | None = {}
    if reason != TEST_STOP and run.saved_step != run.state.step:
        save(run)
    if reason == SIGNAL:
        logger.warning(
            "stopped by a signal at step %d; `--resume` continues from %s",
            run.state.step,
            run.last_checkpoint,
        )
    elif reason in (DONE, TIME):
        if run.cfg.use_lora and run.cfg.lora.merge_at_end and not _merge_is_current(run.last_checkpoint):
            export_merged_lora(run.accelerator, run.opt.evaluated, run.cfg.output_dir)  # <output_dir>/merged
        final = _final_evaluation(run)
    stopped_early = reason != DONE or final is None  # None: a signal stopped the final evaluation
    agent = run.accelerator.unwrap_model(run.opt.evaluated)
    return TrainResult(
        run.state, run.last_checkpoint, final or {}, stopped_early, agent, run.accelerator.is_main_process
    )


def _final_evaluation(run: Run) -> dict[str, float] | None:
    """The figures of `data.test_split` (`{}` with `validation.final_eval=false`); None when SIGTERM / SIGUSR1
    stopped the pass: no figures, as a stop mid-training."""
    if run.test_loader is None:
        return {}
    stops, step = run.stops, run.state.step
    stops.stage = "the final evaluation"
    logger.info("final evaluation on %s: %d samples", run.cfg.data.test_split, len(run.test_indices))
    final = evaluate(
        run.opt.evaluated, run.test_loader, run.accelerator, "test", lambda: stops.reason() == SIGNAL
    )
    if final is None:
        logger.warning(
            "stopped by a signal during the final evaluation; nothing written as its result; `--resume` "
            "evaluates %s",
            run.last_checkpoint,
        )
        return None
    if run.cfg.stage == STAGE_NAVIGATION:
        final["majority_class_rate"] = majority_class_rate(run.data.train, run.data.test, run.test_indices)
    log_metrics(run.accelerator, "test", final, step)
    return final


def _merge_is_current(checkpoint: Path | None) -> bool:
    """Whether `<output_dir>/merged` already holds the merge of `checkpoint` (a resume with nothing left to
    train after a finished run): then it is not written again."""
    return checkpoint is not None and merged_model_of(checkpoint) is not None

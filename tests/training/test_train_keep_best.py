"""`checkpoint.keep_best`: the best validation pass so far is saved and named by `checkpoints/best`."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from conftest import make_config, train_in_process

from openfly_agent import constants as C
from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.training.best import BEST_RECORD_NAME, BestMetric
from openfly_agent.training.checkpoint import checkpoint_name
from openfly_agent.training.config import CheckpointConfig


def test_a_loss_is_best_lowest_an_accuracy_highest_and_nan_or_absent_never():
    loss = BestMetric("val/loss")
    assert (
        loss.offer({"loss": 2.0}, 1) and not loss.offer({"loss": 2.5}, 2) and not loss.offer({"loss": 2.0}, 3)
    )
    assert loss.offer({"loss": 1.5}, 4) and (loss.value, loss.step) == (1.5, 4)
    accuracy = BestMetric("val/action_accuracy")
    assert accuracy.offer({"action_accuracy": 0.2}, 1) and accuracy.offer({"action_accuracy": 0.3}, 2)
    assert not accuracy.offer({"action_accuracy": 0.1}, 3) and accuracy.step == 2
    iou = BestMetric("val/box_iou")
    assert not iou.offer({"box_iou": math.nan}, 1) and not iou.offer({"loss": 1.0}, 2) and iou.value is None


def test_a_resume_reads_the_best_so_far_from_the_checkpoint_best_names(tmp_path):
    assert BestMetric.resume("val/loss", None) == BestMetric("val/loss")
    (tmp_path / BEST_RECORD_NAME).write_text(json.dumps({"metric": "val/loss", "value": 1.25, "step": 6}))
    assert BestMetric.resume("val/loss", tmp_path) == BestMetric("val/loss", 1.25, 6)
    # another figure than the record's: the next pass becomes the best
    assert BestMetric.resume("val/box_iou", tmp_path) == BestMetric("val/box_iou")


def test_keep_best_needs_a_known_figure_and_validation(generated_dataset, tmp_path):
    with pytest.raises(ValueError, match="checkpoint.keep_best='val/acc': choose one of"):
        CheckpointConfig(keep_best="val/acc")
    cfg = make_config(generated_dataset, tmp_path)
    assert cfg.checkpoint.keep_best is None  # off by default
    with pytest.raises(ValueError, match="follows validation: set --validation.interval > 0"):
        dataclasses.replace(
            cfg,
            checkpoint=CheckpointConfig(keep_best="val/loss"),
            validation=dataclasses.replace(cfg.validation, interval=0),
        )


def test_a_run_validating_every_step_keeps_the_checkpoint_of_its_best_pass(
    generated_dataset, tmp_path, caplog
):
    steps = 4
    cfg = make_config(
        generated_dataset, tmp_path, steps=steps, validation__interval=1, validation__max_samples=8,
        validation__final_eval="false", checkpoint__save_interval=0, checkpoint__keep_last=1,
        checkpoint__keep_best="val/action_accuracy",
    )  # fmt: skip
    with caplog.at_level("WARNING"):
        train_in_process(cfg)
    # the tiny dataset has no val split: validation falls back to test_seen, says so and records it
    assert "has no val split" in caplog.text
    assert json.loads((tmp_path / C.TRAIN_CONFIG_NAME).read_text())["data"]["val_split"] == C.SPLIT_TEST_SEEN
    logged = {}
    for line in (tmp_path / "logs" / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if "val/action_accuracy" in record:
            logged[record["step"]] = record["val/action_accuracy"]
    assert sorted(logged) == list(range(1, steps + 1))
    best_step = max(logged, key=lambda step: (logged[step], -step))  # the first pass of the highest accuracy
    folder = tmp_path / C.CHECKPOINTS_DIR
    best = folder / C.BEST_POINTER_NAME
    assert best.is_symlink() and best.resolve() == (folder / checkpoint_name(best_step)).resolve()
    record = json.loads((best / BEST_RECORD_NAME).read_text())
    assert record == {"metric": "val/action_accuracy", "value": logged[best_step], "step": best_step}
    # keep_last=1 prunes every other checkpoint but the last one; the best stays whatever keep_last says
    kept = sorted(p.name for p in folder.iterdir() if p.name.startswith("step-"))
    assert kept == sorted({checkpoint_name(best_step), checkpoint_name(steps)})
    assert resolve_checkpoint_folder(best) == best  # loaders open it like any checkpoint folder

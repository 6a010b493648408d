"""`train.py --resume=true` refuses settings other than the run's, and records the changes it accepts."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
from conftest import STEPS, make_config, train_args, train_main

from openfly_agent import constants as C
from openfly_agent.training.resume_settings import CONFIG_CHANGES_NAME, RESUMABLE_KEYS
from openfly_agent.utils.config import changed_settings


@pytest.fixture
def run_copy(reference_run, tmp_path):
    """A copy of the finished reference run (4 steps, checkpoints at 2 and 4) to resume."""
    out, _ = reference_run
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    return copy


def test_changed_settings_are_dotted_and_skip_the_allowed_ones():
    stored = {"steps": 4, "optim": {"lr": 0.001, "betas": [0.9, 0.95]}, "logging": {"log_interval": 1}}
    current = {"steps": 8, "optim": {"lr": 0.0003, "betas": [0.9, 0.95]}, "logging": {"log_interval": 5}}
    assert changed_settings(stored, current) == {
        "logging.log_interval": (1, 5),
        "optim.lr": (0.001, 0.0003),
        "steps": (4, 8),
    }
    assert changed_settings(stored, current, RESUMABLE_KEYS) == {"optim.lr": (0.001, 0.0003)}


def test_a_resume_with_another_lr_is_refused_naming_it(run_copy, generated_dataset, capsys):
    recorded = (run_copy / C.TRAIN_CONFIG_NAME).read_bytes()
    args = train_args(
        generated_dataset,
        run_copy,
        steps=STEPS,
        resume="true",
        optim__lr="3e-4",
        data__history__mode="uniform",
    )
    assert train_main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("train.py: --resume=true with other settings than "), err[0]
    assert "optim.lr: 0.001 -> 0.0003" in err[0] and "data.history.mode: 'keyframes' -> 'uniform'" in err[0]
    assert (run_copy / C.TRAIN_CONFIG_NAME).read_bytes() == recorded
    assert not (run_copy / CONFIG_CHANGES_NAME).exists()
    assert sorted(p.name for p in (run_copy / "checkpoints").iterdir()) == [
        "last",
        "step-000002",
        "step-000004",
    ]


def test_a_resume_with_more_steps_trains_on_and_appends_the_change(
    reference_run, run_copy, generated_dataset, capsys
):
    recorded = (run_copy / C.TRAIN_CONFIG_NAME).read_bytes()
    for steps in (STEPS + 1, STEPS + 2):
        args = train_args(
            generated_dataset, run_copy, steps=steps, resume="true", validation__final_eval="false"
        )
        assert train_main(args) == 0, capsys.readouterr().err[-2000:]
    assert (run_copy / C.TRAIN_CONFIG_NAME).read_bytes() == recorded  # the first steps' settings stay
    entries = [json.loads(line) for line in (run_copy / CONFIG_CHANGES_NAME).read_text().splitlines()]
    assert [(e["step"], e["checkpoint"]) for e in entries] == [
        (STEPS, "step-000004"),
        (STEPS + 1, "step-000005"),
    ]
    assert entries[0]["changes"] == {
        "output_dir": {"from": str(reference_run[0]), "to": str(run_copy)},  # the run was copied here
        "steps": {"from": STEPS, "to": STEPS + 1},
        "validation.final_eval": {"from": True, "to": False},
    }
    assert entries[1]["changes"] == {"steps": {"from": STEPS + 1, "to": STEPS + 2}}
    assert all(e["time"].endswith("Z") for e in entries)


def test_a_setting_the_checkpoint_does_not_record_is_not_a_change(reference_run, generated_dataset, tmp_path):
    """A run recorded before a TrainConfig field existed still resumes after the upgrade."""
    from openfly_agent.training.preflight import resolve_val_split
    from openfly_agent.training.resume_settings import resume_changes

    out, _ = reference_run
    checkpoint = tmp_path / "step-000004"
    shutil.copytree(
        out / "checkpoints" / "step-000004", checkpoint, ignore=shutil.ignore_patterns("training_*")
    )
    stored = json.loads((checkpoint / C.TRAIN_CONFIG_NAME).read_text())
    del stored["optim"]["ema_decay"]  # as if written before optim.ema_decay was added
    (checkpoint / C.TRAIN_CONFIG_NAME).write_text(json.dumps(stored))
    cfg = make_config(generated_dataset, out, steps=STEPS + 1, resume="true")
    cfg = dataclasses.replace(cfg, data=resolve_val_split(cfg.data)[0])  # as train() does first
    assert resume_changes(cfg, checkpoint) == {"steps": (STEPS, STEPS + 1)}

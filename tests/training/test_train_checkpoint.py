"""Checkpoint folders: atomic commit, the `last` pointer, pruning, crash leftovers, trainer state."""

from __future__ import annotations

import json

import pytest

from openfly_agent.training.checkpoint import CheckpointManager, checkpoint_name
from openfly_agent.training.state import TrainerState


def _save(manager: CheckpointManager, step: int, payload: str = "w") -> None:
    staging = manager.begin(step)
    (staging / "weights.txt").write_text(f"{payload}{step}")
    manager.commit(step)


def test_commit_renames_and_points_last(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=3)
    assert manager.latest() is None
    _save(manager, 5)
    _save(manager, 10)
    assert manager.latest() == tmp_path / "checkpoints" / "step-000010"
    assert (tmp_path / "checkpoints" / "last").read_text().strip() == "step-000010"
    assert not any(p.name.startswith(".tmp-") for p in (tmp_path / "checkpoints").iterdir())


def test_keep_last_prunes_oldest(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=2)
    for step in (1, 2, 3, 4):
        _save(manager, step)
    assert [p.name for p in manager.complete_checkpoints()] == ["step-000003", "step-000004"]


def test_crash_mid_write_keeps_previous_checkpoint(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=1)
    _save(manager, 3)
    staging = manager.begin(6)
    (staging / "weights.txt").write_text("half")  # the process dies here: no commit
    fresh = CheckpointManager(tmp_path, keep_last=1)  # a new run starts
    assert fresh.latest().name == "step-000003"
    assert (fresh.latest() / "weights.txt").read_text() == "w3"
    assert [p.name for p in fresh.remove_stale_staging()] == [".tmp-step-000006"]
    assert fresh.latest().name == "step-000003"


def test_resave_same_step_replaces_it(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=2)
    _save(manager, 4, payload="a")
    _save(manager, 4, payload="b")
    assert (manager.latest() / "weights.txt").read_text() == "b4"
    assert len(manager.complete_checkpoints()) == 1


def test_latest_falls_back_when_pointer_is_stale(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=3)
    _save(manager, 1)
    _save(manager, 2)
    (tmp_path / "checkpoints" / "last").write_text("step-000099\n")
    assert manager.latest().name == "step-000002"


def test_checkpoint_name_and_keep_last_validation(tmp_path):
    assert checkpoint_name(123) == "step-000123"
    with pytest.raises(ValueError, match="keep_last"):
        CheckpointManager(tmp_path, keep_last=0)


def test_trainer_state_round_trip_and_errors(tmp_path):
    state = TrainerState(step=7, epoch=1, step_in_epoch=2, samples_seen=56, world_size=2, train_seconds=93)
    state.save(tmp_path)
    assert TrainerState.load(tmp_path) == state
    (tmp_path / "trainer_state.json").write_text(json.dumps({"step": -1}))
    with pytest.raises(ValueError, match="'step' must be a non-negative integer"):
        TrainerState.load(tmp_path)
    with pytest.raises(FileNotFoundError, match="not a complete training checkpoint"):
        TrainerState.load(tmp_path / "nothing")

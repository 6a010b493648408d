"""Checkpoint folders: atomic commit, the `last` pointer, pruning, crash leftovers, trainer state, file modes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.training.checkpoint import CheckpointManager, checkpoint_name
from openfly_agent.training.state import TrainerState
from openfly_agent.utils.processes import run_group

REPO_ROOT = Path(__file__).resolve().parents[2]


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
    last = tmp_path / "checkpoints" / "last"
    assert last.is_symlink() and os.readlink(last) == "step-000010"  # relative: the run folder can move
    assert (last / "weights.txt").read_text() == "w10"
    assert not any(p.name.startswith(".tmp-") for p in (tmp_path / "checkpoints").iterdir())


def test_best_is_a_link_kept_whatever_keep_last_until_mark_best_moves_it(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=1)
    assert manager.best() is None
    _save(manager, 1)
    manager.mark_best(1)
    best = tmp_path / "checkpoints" / "best"
    assert best.is_symlink() and os.readlink(best) == "step-000001" and manager.best() == manager.final_dir(1)
    _save(manager, 2)
    _save(manager, 3)
    assert [p.name for p in manager.complete_checkpoints()] == ["step-000001", "step-000003"]
    manager.mark_best(3)  # the old best is pruned now
    assert [p.name for p in manager.complete_checkpoints()] == ["step-000003"]
    assert manager.best() == manager.latest() == manager.final_dir(3)


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
    last = tmp_path / "checkpoints" / "last"
    last.unlink()
    os.symlink("step-000099", last)  # dangling
    assert manager.latest().name == "step-000002"
    last.unlink()
    last.write_text("step-000099\n")  # a pointer file of an older run, stale
    assert manager.latest().name == "step-000002"


def test_pointer_file_of_an_older_run_is_read_then_replaced_by_a_symlink(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=3)
    _save(manager, 1)
    _save(manager, 2)
    last = tmp_path / "checkpoints" / "last"
    last.unlink()
    last.write_text("step-000001\n")  # how runs were written before
    assert manager.latest().name == "step-000001"
    _save(manager, 3)  # the resumed run commits: `last` becomes a symlink
    assert last.is_symlink() and os.readlink(last) == "step-000003"


def test_a_crash_between_link_and_rename_leaves_a_link_that_start_up_removes(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=2)
    _save(manager, 1)
    os.symlink("step-000001", tmp_path / "checkpoints" / ".tmp-last", target_is_directory=True)
    assert [p.name for p in manager.remove_stale_staging()] == [".tmp-last"]
    assert (tmp_path / "checkpoints" / "step-000001" / "weights.txt").read_text() == "w1"  # not followed


def _plain_file_mode(folder: Path) -> int:
    """The mode the umask gives a plain file created now (written with open(), as config.json is)."""
    probe = folder / "plain.txt"
    probe.write_text("x")
    mode = probe.stat().st_mode & 0o777
    probe.unlink()
    return mode


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_committed_weights_follow_the_umask(tmp_path, umask):
    import torch
    from safetensors.torch import save_file

    old = os.umask(umask)
    try:
        manager = CheckpointManager(tmp_path, keep_last=1)
        staging = manager.begin(1)
        save_file({"w": torch.zeros(2)}, str(staging / "model.safetensors"))
        (staging / "training_state").mkdir()
        save_file({"w": torch.zeros(2)}, str(staging / "training_state" / "model.safetensors"))
        (staging / "config.json").write_text("{}")
        final = manager.commit(1)
        want = _plain_file_mode(tmp_path)
    finally:
        os.umask(old)
    assert want == 0o666 & ~umask
    for name in ("model.safetensors", "training_state/model.safetensors", "config.json"):
        assert (final / name).stat().st_mode & 0o777 == want, name


def test_hugging_face_loaders_open_last_in_a_fresh_process(tmp_path):
    """AutoConfig / AutoModel / AutoProcessor with trust_remote_code on `<run>/checkpoints/last`."""
    import torch

    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import make_model_config
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    text = ["fly to the red tower and stop", "turn left at the blue dome then ascend"]
    tokenizer = train_bpe_tokenizer(text * 8, vocab_size=300, out_dir=tmp_path / "tokenizer")
    torch.manual_seed(0)
    agent = OpenFlyAgent.from_model_config(make_model_config("tiny"), tokenizer=tokenizer).eval()
    manager = CheckpointManager(tmp_path / "run", keep_last=1)
    agent.save_pretrained(manager.begin(7))
    manager.commit(7)
    last = tmp_path / "run" / "checkpoints" / "last"
    assert resolve_checkpoint_folder(last) == tmp_path / "run" / "checkpoints" / "step-000007"
    code = (
        "import json, sys\n"
        "from transformers import AutoConfig, AutoModel, AutoProcessor\n"
        "path = sys.argv[1]\n"
        "config = AutoConfig.from_pretrained(path, trust_remote_code=True)\n"
        "model = AutoModel.from_pretrained(path, trust_remote_code=True)\n"
        "processor = AutoProcessor.from_pretrained(path, trust_remote_code=True)\n"
        "print(json.dumps([type(config).__name__, type(model).__name__, type(processor).__name__,\n"
        "                  sum(p.numel() for p in model.parameters())]))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGINGFACE_"))}
    env.update(HF_HOME=str(tmp_path / "hf_home"), HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO_ROOT))
    done = run_group(
        [sys.executable, "-c", code, str(last)], timeout=300, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL
    )
    assert done.returncode == 0, done.stderr[-3000:]
    names = json.loads(done.stdout.strip().splitlines()[-1])
    assert names == [
        "OpenFlyAgentConfig",
        "OpenFlyAgent",
        "OpenFlyProcessor",
        sum(p.numel() for p in agent.parameters()),
    ]


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


def test_a_last_folder_left_by_a_copy_that_followed_the_link_is_replaced(tmp_path):
    """`shutil.copytree` of a run turns `last` into a real folder; the next commit makes it a link again."""
    import shutil

    root = tmp_path / "run" / "checkpoints"
    (root / "step-000002").mkdir(parents=True)
    (root / "step-000002" / "model.safetensors").write_bytes(b"x")
    os.symlink("step-000002", root / "last")
    copy = tmp_path / "copy"
    shutil.copytree(tmp_path / "run", copy)
    assert (copy / "checkpoints" / "last").is_dir() and not (copy / "checkpoints" / "last").is_symlink()
    manager = CheckpointManager(copy, keep_last=5)
    (manager.begin(4) / "model.safetensors").write_bytes(b"y")
    manager.commit(4)
    assert os.readlink(copy / "checkpoints" / "last") == "step-000004"

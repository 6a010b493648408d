"""train.py's bad inputs: one line on stderr, exit code 2, no traceback and no empty run folder left.

Also under a two-process launch: the line is printed once (by rank 0), not once per process.
"""

from __future__ import annotations

import importlib.util
import shutil
import sys

import pytest
from conftest import REPO_ROOT, run_script, train_args, train_main


@pytest.fixture(scope="module")
def truncated_checkpoint(reference_run, tmp_path_factory):
    """A copy of the reference run's last checkpoint whose model.safetensors lost its second half."""
    out, _ = reference_run
    folder = tmp_path_factory.mktemp("truncated") / "step-000004"
    shutil.copytree(
        out / "checkpoints" / "step-000004", folder, ignore=shutil.ignore_patterns("training_state")
    )
    weights = folder / "model.safetensors"
    with open(weights, "r+b") as f:
        f.truncate(weights.stat().st_size // 2)
    return folder


CASES = {
    "truncated_init": (
        lambda ckpt, data: {"init__checkpoint": ckpt},
        "train.py: init.checkpoint: {ckpt}/model.safetensors is not a readable safetensors file (",
    ),
    "init_is_a_dataset": (
        lambda ckpt, data: {"init__checkpoint": data},
        "train.py: init.checkpoint: {data} is not a checkpoint folder (no config.json) nor a training run",
    ),
    "missing_llm_tokenizer_path": (
        lambda ckpt, data: {"model__llm__tokenizer_path": f"{data}/no-tokenizer"},
        "train.py: --model.llm.tokenizer_path {data}/no-tokenizer is not a folder",
    ),
    "not_an_int": (lambda ckpt, data: {"steps": "abc"}, "train.py: --steps: expected an int, got 'abc'"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_and_leaves_no_folder(
    case, truncated_checkpoint, generated_dataset, tmp_path, capsys
):
    overrides, expected = CASES[case]
    output_dir = tmp_path / "run"
    args = train_args(generated_dataset, output_dir, **overrides(truncated_checkpoint, generated_dataset))
    assert train_main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(expected.format(ckpt=truncated_checkpoint, data=generated_dataset)), err[0]
    assert not output_dir.exists()


def test_a_failed_start_removes_the_parent_folders_it_made(tmp_path, capsys):
    """A missing data root in a fresh working directory: neither the run folder nor the `outputs/train/` made for
    it stays; a parent that was there before the run stays too."""
    args = ["--data.root", str(tmp_path / "no-dataset"), "--logging.tracker=none"]
    assert train_main([*args, f"--output_dir={tmp_path / 'outputs' / 'train' / 'run'}"]) == 2
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "outputs").mkdir()
    assert train_main([*args, f"--output_dir={tmp_path / 'outputs' / 'train' / 'run'}"]) == 2
    assert [path.name for path in tmp_path.rglob("*")] == ["outputs"]
    assert len(capsys.readouterr().err.strip().splitlines()) == 2  # one line per run


def test_a_preflight_error_under_a_launcher_is_printed_once(tmp_path):
    args = [
        "--data.root", str(tmp_path / "no-dataset"),
        f"--output_dir={tmp_path / 'run'}", "--logging.tracker=none",
    ]  # fmt: skip
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    done = run_script(args, launcher=torchrun, timeout=120)
    lines = [line for line in done.stderr.splitlines() if line.startswith("train.py:")]
    assert lines == [
        f"train.py: dataset root {tmp_path / 'no-dataset'} does not exist: generate it (python -m "
        f"openfly_agent.toolchain generate --output_dir={tmp_path / 'no-dataset'}), or download the released "
        "OpenFly data as data_cards/openfly_released.md says and pass its folder as --data.root"
    ], done.stderr[-3000:]
    assert "failed (exitcode: 2)" in done.stderr  # each process exited 2; the launcher reports that
    assert not (tmp_path / "run").exists()


def test_a_process_other_than_rank_0_says_the_error_once_its_wait_is_over(monkeypatch, capsys):
    """Rank 0 is left the time to say an error; a process rank 0 did not stop by then says it itself."""
    spec = importlib.util.spec_from_file_location("train_entry_point", REPO_ROOT / "train.py")
    entry = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(entry)
    waits = []
    monkeypatch.setattr(entry.time, "sleep", waits.append)
    monkeypatch.setenv("RANK", "1")
    entry.say_error("dataset root x does not exist")
    assert waits == [entry.RANK_ERROR_GRACE_S]
    assert capsys.readouterr().err == "train.py: dataset root x does not exist\n"
    monkeypatch.setenv("RANK", "0")
    entry.say_error("dataset root x does not exist")
    assert waits == [entry.RANK_ERROR_GRACE_S]  # rank 0 says it at once

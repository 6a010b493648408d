"""FSDP2 (`fully_shard`) on the CPU over gloo, two processes: training follows an unsharded copy, and a sharded
torch.distributed.checkpoint save / load restores weights and AdamW states exactly.

accelerate 1.15 does not form an FSDP run on the CPU (its state only switches to FSDP for GPU-like device
types; on the CPU it stays MULTI_CPU), so the worker applies what accelerate's FSDP2 path applies (the
checkpoint wrapper and `fully_shard` on each Llama decoder layer and ViT block, then the root) with torch's own
calls (docs/TRAINING.md, "FSDP and activation checkpointing on the CPU").
"""

from __future__ import annotations

import json
import re
import sys
import warnings
from pathlib import Path

import pytest
from conftest import run_script

WORKER = Path(__file__).with_name("fsdp_worker.py")
SIGNAL_DEATH = re.compile(r"exitcode\s*:\s*-\d+")  # torchrun's failure report of a rank a signal ended
ERROR_LINE = re.compile(r"terminate called|Error|Exception|Assertion|what\(\)")
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]


def killed_by_a_signal(stderr: str) -> bool:
    """Whether torchrun reports a rank ended by a signal (SIGABRT, SIGSEGV: negative exit code)."""
    return bool(SIGNAL_DEATH.search(stderr))


def first_error(stderr: str) -> str:
    """The first line of the workers' output that names an error (the rank that failed first), or ''."""
    return next((line.strip() for line in stderr.splitlines() if ERROR_LINE.search(line)), "")


@pytest.fixture(scope="module")
def fsdp_results(tmp_path_factory) -> dict[str, dict]:
    from bench.train_throughput import instructions  # the synthetic batches' words
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    out = tmp_path_factory.mktemp("fsdp")
    tokenizer = out / "tokenizer"
    train_bpe_tokenizer(instructions(16), vocab_size=320, out_dir=tokenizer)
    done = run_script(["--tokenizer", str(tokenizer), "--out", str(out)], TORCHRUN, 300, WORKER)
    if done.returncode != 0 and killed_by_a_signal(done.stderr):
        # Once in a loaded suite run (1 of 4 on 2026-11-28) rank 0 died of SIGABRT (its message cut from the
        # report) and rank 1 then saw gloo's "Connection reset by peer"; 3 + 3 reruns under load did not repeat it.
        # A rank the runtime aborted says nothing of FSDP: run it once more, keeping the first attempt's log.
        (out / "first_attempt_stderr.txt").write_text(done.stderr)
        warnings.warn(
            f"FSDP worker: a rank was killed by a signal; retrying once ({first_error(done.stderr)})",
            stacklevel=2,
        )
        done = run_script(["--tokenizer", str(tokenizer), "--out", str(out)], TORCHRUN, 300, WORKER)
    assert done.returncode == 0, f"{first_error(done.stderr)}\n...\n{done.stderr[-3000:]}"
    return {name: json.loads((out / f"{name}.json").read_text()) for name in ("tiny", "vit-llama")}


@pytest.mark.parametrize("model", ["tiny", "vit-llama"])
def test_fully_shard_trains_as_the_unsharded_model_and_resumes_exactly(fsdp_results, model):
    result = fsdp_results[model]
    assert result["world_size"] == 2
    assert result["sharded_params"] > 100 and abs(result["local_fraction"] - 0.5) < 0.01  # half on each rank
    # each rank saw the same batch: the averaged gradients are the unsharded ones
    assert result["losses"] == pytest.approx(result["reference_losses"], rel=1e-5)
    assert result["losses"][-1] < result["losses"][0]
    assert result["weights_vs_unsharded"] < 1e-5
    # one shard file per rank, and the loaded weights and AdamW states are the saved ones, bit for bit
    assert result["checkpoint_files"] == [".metadata", "__0_0.distcp", "__1_0.distcp"]
    assert result["saved_tensors"] > 3 * result["sharded_params"]  # weights + exp_avg + exp_avg_sq + step
    assert result["resumed_vs_saved"] == 0.0
    assert result["next_resumed_loss"] == result["next_loss"] and result["after_step_difference"] == 0.0


def test_only_a_rank_killed_by_a_signal_is_retried():
    aborted = "  exitcode  : -6 (pid: 15577)\n  error_file: <N/A>\n  traceback : Signal 6 (SIGABRT) received by PID 15577"
    assert killed_by_a_signal(aborted)
    assert not killed_by_a_signal("  exitcode  : 1 (pid: 15577)\n  traceback : AssertionError: losses differ")
    stderr = (
        "W1128 warning\n[rank0]: terminate called after throwing an instance of 'gloo::IoException'\nmore"
    )
    assert (
        first_error(stderr) == "[rank0]: terminate called after throwing an instance of 'gloo::IoException'"
    )

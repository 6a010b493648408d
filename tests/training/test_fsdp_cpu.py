"""FSDP2 (`fully_shard`) on the CPU over gloo, two processes: training follows an unsharded copy, and a sharded
torch.distributed.checkpoint save / load restores weights and AdamW states exactly.

accelerate 1.15 does not form an FSDP run on the CPU (its state only switches to FSDP for GPU-like device
types; on the CPU it stays MULTI_CPU), so the worker applies what accelerate's FSDP2 path applies (the
checkpoint wrapper and `fully_shard` on each Llama decoder layer and ViT block, then the root) with torch's own
calls (docs/TRAINING.md, "FSDP and activation checkpointing on the CPU").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import run_script

WORKER = Path(__file__).with_name("fsdp_worker.py")
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]


@pytest.fixture(scope="module")
def fsdp_results(tmp_path_factory) -> dict[str, dict]:
    from bench.train_throughput import instructions  # the synthetic batches' words
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    out = tmp_path_factory.mktemp("fsdp")
    tokenizer = out / "tokenizer"
    train_bpe_tokenizer(instructions(16), vocab_size=320, out_dir=tokenizer)
    done = run_script(["--tokenizer", str(tokenizer), "--out", str(out)], TORCHRUN, 300, WORKER)
    assert done.returncode == 0, done.stderr[-3000:]
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

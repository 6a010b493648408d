"""Real processes: two gloo processes equal one with the same global batch; SIGKILL mid-run, then resume."""

from __future__ import annotations

import json
import re
import signal
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from conftest import (
    REPO_ROOT,
    STEPS,
    checkpoint_weights,
    make_config,
    run_script,
    start_script,
    train_args,
    train_in_process,
    train_losses,
    with_val_split,
)

from openfly_agent.data.collator import NavigationCollator
from openfly_agent.training.builder import load_splits
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.evaluate import evaluate, make_eval_loader
from openfly_agent.utils.processes import run_group

EXIT_PROBE = Path(__file__).with_name("exit_probe.py")


def _final_test_metrics(output_dir) -> dict[str, float]:
    records = [json.loads(line) for line in (output_dir / "logs" / "metrics.jsonl").read_text().splitlines()]
    return {k: v for record in records for k, v in record.items() if k.startswith("test/")}


# The tiny preset's ResNet normalises with BatchNorm, over each process's own micro-batch under DDP (as without
# SyncBatchNorm on GPUs), and its box token jitters the training box with random noise drawn per process (like
# dropout), so equality between 1 and 2 processes is checked with the batch-independent ViTs and no jitter.
VIT = {
    "model__vision__type": "tiny", "model__vision__image_size": 64, "model__vision__patch_size": 8,
    "model__action_head__box_token_jitter": 0.0,
}  # fmt: skip


@pytest.fixture(scope="module")
def vit_reference_run(generated_dataset, tmp_path_factory):
    """`reference_run` with the two small ViTs as the backbone."""
    out = tmp_path_factory.mktemp("vit_reference")
    return out, train_in_process(make_config(generated_dataset, out, steps=STEPS, **VIT))


def test_two_processes_give_the_same_losses_and_weights_as_one(
    vit_reference_run, generated_dataset, tmp_path
):
    reference_dir, reference = vit_reference_run
    # 9 test samples over 2 processes x 4: one round-robin group of 8, then rank 1 pads with a weight-0 batch
    args = [str(REPO_ROOT / "train.py")] + train_args(
        generated_dataset, tmp_path, steps=STEPS, validation__final_max_samples=9, **VIT
    )
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    done = run_script(args, launcher=torchrun, script=EXIT_PROBE)
    assert done.returncode == 0, done.stderr[-3000:]
    # Each rank destroyed its process group exactly once, after the DDP model was gone (a live Reducer would
    # hold the group's last reference and could deadlock the rank at exit; scripts/stress_train_exit.py).
    probes = sorted(re.findall(r"exit-probe: rank=(\d) destroy_calls=(\d+) ddp_alive=(-?\d+) initialized=(True|False)",
                               done.stderr))  # fmt: skip
    assert probes == [("0", "1", "0", "False"), ("1", "1", "0", "False")], done.stderr[-3000:]
    # rank 0 alone logs INFO lines: each appears once, not once per process
    assert done.stderr.count(f"run: {STEPS} steps") == 1, done.stderr[-3000:]
    one, two = train_losses(reference_dir), train_losses(tmp_path)
    assert sorted(two) == list(range(1, STEPS + 1))
    assert two == pytest.approx(one, rel=1e-5)
    expected = checkpoint_weights(reference_dir / "checkpoints" / f"step-{STEPS:06d}")
    found = checkpoint_weights(tmp_path / "checkpoints" / f"step-{STEPS:06d}")
    for key in expected:  # float reduction order differs; Adam's 1/sqrt(v) amplifies it on tiny gradients
        torch.testing.assert_close(found[key], expected[key], rtol=1e-4, atol=1e-5, msg=key)

    # the final offline evaluation covers exactly the 9 samples, as one process over the same 9 does
    single = SimpleNamespace(device=torch.device("cpu"), num_processes=1, process_index=0)
    cfg = with_val_split(make_config(generated_dataset, reference_dir, **VIT))
    test_set = load_splits(cfg.data, cfg.model.grounding).dataset(cfg.data.test_split, cfg, reference.agent)
    collate = NavigationCollator(
        reference.agent.processor, cfg.model.memory.capacity, cfg.model.keyframes.set_size
    )
    loader, indices = make_eval_loader(test_set, 9, 4, single, collate)
    one_process = evaluate(reference.agent, loader, single)
    two_processes = _final_test_metrics(tmp_path)
    assert len(indices) == 9 and two_processes["test/samples"] == one_process["samples"] == 9
    assert two_processes["test/action_accuracy"] == pytest.approx(one_process["action_accuracy"])
    assert two_processes["test/box_iou"] == pytest.approx(one_process["box_iou"], rel=1e-3)


def test_sigkill_mid_run_leaves_a_valid_checkpoint_and_resume_matches(generated_dataset, tmp_path):
    """Killed, then resumed: the weights of an uninterrupted run, bit for bit. Every run is a fresh train.py
    process, as users run it (in-process training after an in-process eval.py in the same pytest process was
    seen to differ in the last bits from a fresh process)."""
    reference_dir = tmp_path / "reference"
    done = run_script(
        train_args(generated_dataset, reference_dir, steps=STEPS, validation__final_eval="false")
    )
    assert done.returncode == 0, done.stderr[-3000:]
    args = train_args(generated_dataset, tmp_path / "run", steps=STEPS, checkpoint__save_interval=1)
    manager = CheckpointManager(tmp_path / "run", keep_last=5)
    with start_script(args) as process:
        deadline = time.monotonic() + 240
        while manager.latest() is None or manager.latest().name < "step-000002":
            assert process.poll() is None, "training ended before it could be killed"
            assert time.monotonic() < deadline, "no checkpoint appeared"
            time.sleep(0.05)
        process.send_signal(signal.SIGKILL)  # at an arbitrary point after step 2: computing or writing step 3
        process.wait()
    latest = CheckpointManager(tmp_path / "run", keep_last=5).latest()
    assert latest is not None and (latest / "trainer_state.json").is_file()
    resume = train_args(
        generated_dataset, tmp_path / "run", steps=STEPS, checkpoint__save_interval=1, resume="true",
        validation__final_eval="false",
    )  # fmt: skip
    resumed = run_script(resume)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert re.search(rf"starting at step {latest.name[-1]}\b", resumed.stderr), resumed.stderr[-3000:]
    assert not any(p.name.startswith(".tmp-") for p in (tmp_path / "run" / "checkpoints").iterdir())
    expected = checkpoint_weights(reference_dir / "checkpoints" / f"step-{STEPS:06d}")
    found = checkpoint_weights(tmp_path / "run" / "checkpoints" / f"step-{STEPS:06d}")
    for key in expected:
        torch.testing.assert_close(found[key], expected[key], rtol=0, atol=0, msg=key)


def test_each_epoch_reaches_the_dataset_with_two_processes(generated_dataset, tmp_path):
    """`random` history draws change with the epoch under a 2-process launch, and every process sees the draws
    of the current epoch (accelerate's loader alone forwards the epoch to the dataset with one process only)."""
    from epoch_worker import describe, make_dataset

    args = train_args(generated_dataset, tmp_path / "run", data__history__mode="random")
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    command = [*torchrun, str(Path(__file__).with_name("epoch_worker.py")), str(tmp_path), *args]
    done = run_group(command, timeout=300, cwd=REPO_ROOT, env=_env())
    assert done.returncode == 0, done.stderr[-3000:]
    seen = [tuple(r) for rank in (0, 1) for r in json.loads((tmp_path / f"rank{rank}.json").read_text())]
    assert {r[0] for r in seen} == {0, 1} and len(seen) > 20  # (epoch, episode, step, memory digest)
    # what one process computes for the same samples, epoch by epoch
    dataset = make_dataset(make_config(generated_dataset, tmp_path / "run", data__history__mode="random"))
    index = {(e.episode_id, t): i for i in range(len(dataset)) for e, t in [dataset.locate(i)]}
    samples = sorted({index[(episode_id, step)] for _, episode_id, step, _ in seen})
    expected = {}
    for epoch in (0, 1):
        dataset.set_epoch(epoch)
        for episode_id, step, digest in describe([dataset[i] for i in samples]):
            expected[(epoch, episode_id, step)] = digest
    wrong = [r for r in seen if expected[r[:3]] != r[3]]
    assert not wrong, f"{len(wrong)} of {len(seen)} samples carry another epoch's draws, e.g. {wrong[:2]}"
    changed = [key for key in expected if key[0] == 0 and expected[key] != expected[(1, *key[1:])]]
    assert len(changed) > len(samples) // 4  # the draws really change between epochs


def _env() -> dict[str, str]:
    import os

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TOKENIZERS_PARALLELISM": "false"}
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO_ROOT), str(Path(__file__).parent), env.get("PYTHONPATH", "")]
    )
    return env

"""Model FLOPs, MFU and the step-time split of the training log (training/throughput.py, step_timer.py)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from openfly_agent import constants as C
from openfly_agent.model.config import tiny_config
from openfly_agent.training.step_timer import PHASES, StepTimer, log_line
from openfly_agent.training.throughput import StepFlops, device_peak_flops, mfu
from openfly_agent.training.trackers import read_metrics


def toy_flops(**overrides) -> StepFlops:
    toy = StepFlops(
        vision_frame=100.0,
        vision_backward=0.0,  # frozen backbone
        projector_params=10,
        projector_trainable=10,
        projector_input_grads=False,
        llm_params=1000,
        llm_trainable=50,  # LoRA
        llm_input_grads=True,
        layers=2,
        width=4,
        model_cfg=tiny_config(),
    )
    return dataclasses.replace(toy, **overrides)


def test_step_flops_by_hand():
    rows = torch.tensor([3, 5])
    # vision: 100 x 2 frames, forward only; projector: 2 x (10 + 10) x 6 tokens (no input gradients);
    # LLM matrices: 2 x (1000 x 2 + 50) x 8 tokens; attention: 4 x 2 x 4 x (1 + 2) x (3^2 + 5^2)
    expected = 200 + 240 + 32_800 + 96 * 34
    assert float(toy_flops().flops(2, rows, 6)) == expected
    # a full fine-tune of every part: vision 3x forward, projector and LLM 6 N per token
    full = toy_flops(vision_backward=2.0, projector_input_grads=True, llm_trainable=1000).flops(2, rows, 6)
    assert float(full) == 600 + 6 * 10 * 6 + 6 * 1000 * 8 + 96 * 34


def test_batch_counts_real_frames_and_tokens():
    cfg = tiny_config()  # 8 x 8 = 64 patches, 1 token per memory set
    mask = torch.zeros(2, 2, 5, dtype=torch.bool)  # (B, K, S)
    mask[0, 0, :3] = True
    mask[0, 1, 4] = True
    mask[1, 1, 0] = True
    batch = {
        C.PIXEL_VALUES: torch.zeros(2, 3, 8, 8, dtype=torch.uint8),
        C.ATTENTION_MASK: torch.tensor([[1] * 10, [1] * 6 + [0] * 4]),
        C.MEMORY_FRAME_MASK: mask,
    }
    count = toy_flops(model_cfg=cfg)
    rows = torch.tensor([10 + 64 + 2, 6 + 64 + 1])
    # 2 current frames + 5 real memory frames; 2 x 64 + 3 visual tokens through the projector
    assert float(count.batch_flops(batch)) == float(count.flops(7, rows, 131))


@pytest.mark.parametrize("stage", ["full", "frozen_vision"])
def test_model_flops_of_the_tiny_agent_are_near_pytorchs_count(stage, tiny_navigation_agent):
    """The count leaves out small parts (grounding head, merging, the LM head) and counts the first layer's
    input gradient that no one computes: within 15 % of what PyTorch's counter sees, in both directions."""
    from torch.utils.flop_counter import FlopCounterMode

    from openfly_agent.model.freeze import freeze

    agent, batch = tiny_navigation_agent
    freeze(agent, stage)
    counter = FlopCounterMode(display=False)
    with counter:
        loss, _ = agent(batch)
        loss.backward()
    agent.zero_grad(set_to_none=True)
    model = float(StepFlops.from_agent(agent).batch_flops(batch))
    assert model == pytest.approx(counter.get_total_flops(), rel=0.15)


@pytest.fixture(scope="module")
def tiny_navigation_agent():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from train_throughput import build_agent, synthetic_batch

    torch.manual_seed(0)
    agent = build_agent("tiny", "cpu").train()
    return agent, synthetic_batch(agent, 2)


def test_peak_and_mfu_without_a_known_peak():
    assert device_peak_flops("cpu") is None  # no CPU peak is made up
    assert device_peak_flops("cpu", override_tflops=100.0) == 100e12
    assert mfu(1e12, 2.0, None) is None
    assert mfu(1e12, 2.0, 1e12) == 0.5


def test_step_timer_splits_each_interval_into_phases(monkeypatch):
    # the marks: start, then per step other, data, forward, backward, optimizer; the report's own mark last
    clock = iter([0.0, 1.0, 1.5, 2.0, 4.0, 4.5, 5.0, 5.5, 6.0, 8.0, 8.5, 9.0])
    monkeypatch.setattr("openfly_agent.training.step_timer.time.perf_counter", lambda: next(clock))
    timer = StepTimer(torch.device("cpu"))
    for steps, _ in enumerate(timer.batches([{"x": 1}, {"x": 2}, {"x": 3}]), 1):
        timer.end("forward")
        timer.end("backward")
        timer.end("optimizer")
        timer.step_done()
        if steps == 2:
            break
    figures = timer.report()
    # per step of the two: data 0.5 (1 -> 1.5, 5 -> 5.5), forward 0.5, backward 2, optimizer 0.5,
    # other (0 -> 1, 4.5 -> 5, 8.5 -> 9) = 2 s over 2 steps
    assert figures["time/data_s"] == 0.5
    assert figures["time/forward_s"] == 0.5
    assert figures["time/backward_s"] == 2.0
    assert figures["time/optimizer_s"] == 0.5
    assert figures["time/other_s"] == 1.0
    assert figures["time/step_s"] == 4.5
    assert math.isclose(sum(figures[f"time/{p}_s"] for p in PHASES), figures["time/step_s"])
    assert "throughput/mfu" not in figures and "throughput/tflops" not in figures
    assert "MFU n/a" in log_line(2, figures, 100.0)


def test_step_timer_flops_and_mfu(monkeypatch):
    clock = iter([0.0, 2.0])  # start, the report: one step of 2 s
    monkeypatch.setattr("openfly_agent.training.step_timer.time.perf_counter", lambda: next(clock))

    class Fixed:
        def batch_flops(self, batch):
            return torch.tensor(3e12, dtype=torch.float64)

    timer = StepTimer(torch.device("cpu"), Fixed(), peak_flops=1e12)
    timer.count({})
    timer.count({})
    timer.step_done()
    figures = timer.report()
    assert figures["throughput/tflops"] == 3.0  # 6e12 FLOPs in 2 s
    assert figures["throughput/mfu"] == 3.0 / 1.0
    assert "MFU 3.000" in log_line(1, figures)


def test_train_log_has_the_time_split_and_model_flops(reference_run):
    out, _ = reference_run
    records = [r for r in read_metrics(out / "logs") if "train/loss" in r]
    assert records and all(r["step"] for r in records)
    for record in records:
        split = sum(record[f"time/{phase}_s"] for phase in PHASES)
        assert split == pytest.approx(record["time/step_s"], rel=1e-6)
        assert record["time/forward_s"] > 0 and record["time/backward_s"] > 0
        assert record["throughput/tflops"] > 0
        assert "throughput/mfu" not in record  # the CPU has no known peak

"""Logged means, token counts, evaluation subsets and the JSON-lines tracker, checked by hand."""

from __future__ import annotations

import math

import pytest
import torch
import yaml
from conftest import make_config, train_in_process
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent import constants as C
from openfly_agent.model.config import tiny_config
from openfly_agent.training.evaluate import eval_indices, shard_eval_batches
from openfly_agent.training.metrics import RunningMeans, ThroughputMeter, count_llm_tokens
from openfly_agent.training.trackers import JsonlTracker, TensorBoardTracker, make_trackers, read_metrics


def test_running_means_weight_box_iou_by_visible_boxes():
    means = RunningMeans()
    means.add({"loss": 2.0, "box_iou": 0.5, "num_visible_boxes": 3.0})
    means.add({"loss": 4.0, "box_iou": 0.0, "num_visible_boxes": 0.0})  # no visible box: IoU does not count
    means.add({"loss": float("nan"), "box_iou": 0.9, "num_visible_boxes": 1.0})
    result = means.pop()
    assert result["loss"] == 3.0
    assert math.isclose(result["box_iou"], (0.5 * 3 + 0.9) / 4)
    assert means.pop() == {}


def test_running_means_keep_all_nan_keys():
    means = RunningMeans()
    means.add({"x": float("nan")})
    assert math.isnan(means.pop()["x"])


def test_llm_token_count_hand_checked():
    cfg = tiny_config()  # 112 px / 14 = 8 x 8 = 64 patches; g = 8 -> 1 token per memory set
    mask = torch.zeros(2, 2, 5, dtype=torch.bool)  # (B, K, S)
    mask[0, 0, :3] = True
    mask[0, 1, 4] = True
    mask[1, 1, 0] = True
    batch = {
        C.INPUT_IDS: torch.zeros(2, 10, dtype=torch.long),
        C.ATTENTION_MASK: torch.tensor([[1] * 10, [1] * 6 + [0] * 4]),
        C.MEMORY_FRAME_MASK: mask,
    }
    assert count_llm_tokens(batch, cfg) == 16 + 2 * 64 + 3 * 1


@settings(max_examples=80, deadline=None)
@given(st.integers(1, 500), st.one_of(st.none(), st.integers(1, 600)))
def test_eval_indices_are_distinct_sorted_and_as_many_as_asked(num_samples, max_samples):
    indices = eval_indices(num_samples, max_samples)
    wanted = num_samples if max_samples is None else min(num_samples, max_samples)
    assert len(indices) == wanted and indices[0] == 0
    assert indices == sorted(set(indices)) and all(0 <= i < num_samples for i in indices)


@settings(max_examples=120, deadline=None)
@given(st.integers(1, 300), st.integers(1, 4), st.integers(1, 16))
def test_eval_shards_cover_every_sample_once_with_equal_forwards(num_samples, world, batch_size):
    indices = eval_indices(num_samples, None)
    shards = [shard_eval_batches(indices, world, rank, batch_size) for rank in range(world)]
    assert len({len(shard) for shard in shards}) == 1  # the same number of forwards on every process
    weighted = [i for shard in shards for batch, weight in shard if weight == 1.0 for i in batch]
    assert sorted(weighted) == indices  # every sample exactly once
    for shard in shards:
        assert all(0 < len(batch) <= batch_size for batch, _ in shard)
        assert all(weight in (0.0, 1.0) for _, weight in shard)
        assert all(batch == [indices[0]] for batch, weight in shard if weight == 0.0)


def test_eval_shards_by_hand():
    # 11 samples, 2 processes, batches of 4: one group of 8 dealt round-robin, the remainder 8, 9, 10 split
    assert shard_eval_batches(list(range(11)), 2, 0, 4) == [([0, 2, 4, 6], 1.0), ([8, 10], 1.0)]
    assert shard_eval_batches(list(range(11)), 2, 1, 4) == [([1, 3, 5, 7], 1.0), ([9], 1.0)]
    # 9 samples: rank 1 has no share of the remainder [8] and pads with a weight-0 forward of sample 0
    assert shard_eval_batches(list(range(9)), 2, 1, 4) == [([1, 3, 5, 7], 1.0), ([0], 0.0)]


def test_throughput_meter_counts(monkeypatch):
    clock = iter([0.0, 2.0, 2.0])
    monkeypatch.setattr("openfly_agent.training.metrics.time.perf_counter", lambda: next(clock))
    meter = ThroughputMeter()
    meter.update(8, 1000)
    meter.update(8, 1000)
    assert meter.report() == {"samples_per_s": 8.0, "tokens_per_s": 1000.0}


def test_jsonl_tracker_round_trip(tmp_path):
    tracker = JsonlTracker("run", tmp_path)
    tracker.store_init_configuration({"optim.lr": 0.1})
    tracker.log({"train/loss": 1.5, "train/box_iou": float("nan")}, step=3)
    assert read_metrics(tmp_path) == [{"step": 3, "train/loss": 1.5, "train/box_iou": "nan"}]
    kinds = make_trackers("tensorboard", "run", tmp_path, "project")
    assert isinstance(kinds[0], JsonlTracker) and isinstance(kinds[1], TensorBoardTracker)


def test_a_corrupt_metrics_line_is_reported_with_its_file_and_line(tmp_path):
    JsonlTracker("run", tmp_path).log({"train/loss": 1.0}, step=1)
    with (tmp_path / "metrics.jsonl").open("a") as f:
        f.write("{truncated\n")
    with pytest.raises(ValueError, match=r"metrics.jsonl, line 2: not valid JSON"):
        read_metrics(tmp_path)
    assert len(make_trackers("none", "run", tmp_path, "project")) == 1


def test_a_resumed_run_logs_each_step_once_in_one_tensorboard_run(generated_dataset, tmp_path):
    """Stopped after step 3 (checkpoint at 2), resumed: step 3 is logged again, and kept once (issue 48)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    settings = {"steps": 4, "checkpoint__save_interval": 2, "logging__tracker": "tensorboard"}
    train_in_process(make_config(generated_dataset, tmp_path, **settings), stop_after=3)
    train_in_process(make_config(generated_dataset, tmp_path, resume="true", **settings))
    logged = [r["step"] for r in read_metrics(tmp_path / "logs") if "train/loss" in r]
    assert logged == [1, 2, 3, 4]
    board = tmp_path / "logs" / "openfly-agent"
    assert [p.name for p in board.iterdir() if p.is_dir()] == []  # no hparams-only "runs" beside the run
    events = EventAccumulator(str(board))
    events.Reload()
    assert [event.step for event in events.Scalars("train/loss")] == [1, 2, 3, 4]
    assert "optim.lr" in yaml.safe_load((board / "hparams.yml").read_text())

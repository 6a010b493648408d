"""bench/step_latency.py: the token counts it reports and one timed step with a full memory."""

from __future__ import annotations

import importlib

from openfly_agent.model.config import make_model_config


def test_history_variants_token_counts():
    bench = importlib.import_module("bench.step_latency")
    seven_b = make_model_config("openfly-7b")
    assert bench.history_variant(seven_b, "keyframe").visual_tokens_per_step() == 258
    assert bench.history_variant(seven_b, "uniform").visual_tokens_per_step() == 256 + 2 * 256
    assert bench.history_variant(make_model_config("tiny"), "uniform").visual_tokens_per_step() == 64 + 2 * 64


def test_time_steps_runs_with_a_full_memory(make_agent):
    bench = importlib.import_module("bench.step_latency")
    agent = make_agent()
    median, mean = bench.time_steps(agent, batch=2, steps=1, warmup=0)  # it asserts a full memory (K = 2)
    assert median > 0 and mean > 0


def test_backbone_step_times_each_stem(monkeypatch, capsys):
    import json

    import torch

    bench = importlib.import_module("bench.backbone_step")
    lines = []
    threads = (
        torch.get_num_threads()
    )  # the bench sets them for the process: later in-process runs need them back
    try:
        for stem in ("resnet", "patch4"):
            argv = ["backbone_step.py", "--stem", stem, "--batch", "2", "--image_size", "64", "--steps", "2"]
            monkeypatch.setattr("sys.argv", [*argv, "--warmup", "0", "--threads", "1"])
            bench.main()
            lines.append(json.loads(capsys.readouterr().out))
    finally:
        torch.set_num_threads(threads)
    assert [line["stem"] for line in lines] == ["resnet", "patch4"]
    assert all(line["ms_per_step"] > 0 for line in lines)
    # only the stem's conv differs: 3 x 64 x (7 x 7 - 4 x 4) weights fewer
    assert lines[0]["parameters"] - lines[1]["parameters"] == 3 * 64 * (49 - 16)

"""bench/offline_compare.py on real runs: per-step hits that add up to the run's own held-out accuracy."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import make_config, train_in_process

from openfly_agent.utils.processes import run_group

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "offline_compare.py"


@pytest.fixture(scope="module")
def no_history_run(generated_dataset, tmp_path_factory):
    """The reference run's settings with the current frame only (no history, no memory), 2 steps."""
    out = tmp_path_factory.mktemp("no_history")
    cfg = make_config(generated_dataset, out, steps=2, data__history__mode="none", model__memory__capacity=0)
    return out, train_in_process(cfg)


def test_a_run_against_itself_scores_its_own_test_accuracy_and_no_difference(reference_run, tmp_path):
    out, result = reference_run
    report = tmp_path / "paired.json"
    done = run_group(
        [sys.executable, str(SCRIPT), "--run", f"a={out}", "--run", f"b={out}", "--max_samples", "8",
         "--batch_size", "3", "--threads", "1", "--json", str(report)],
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(report.read_text())
    assert figures["samples"] == result.final_metrics["samples"] == 8  # the run's own test subset
    # per-step hits, averaged, are the accuracy the training's final pass logged on the same samples
    assert figures["accuracy_a"] == pytest.approx(result.final_metrics["action_accuracy"], abs=1e-9)
    assert figures["diff"] == 0.0 and figures["diff_ci95"] == [0.0, 0.0]
    assert (figures["only_a"], figures["only_b"]) == (0, 0)
    assert "| a | b | b - a (pp)" in done.stdout


def test_runs_with_different_histories_pair_on_the_same_steps(reference_run, no_history_run):
    from bench.analysis.offline_compare import collect_step_hits, paired_hits

    (with_history, _), (without, result) = reference_run, no_history_run
    a = collect_step_hits(with_history, max_samples=8, batch_size=4)
    b = collect_step_hits(without, max_samples=8, batch_size=4)
    assert a.keys == b.keys and len(a.keys) == 8
    assert b.accuracy == pytest.approx(result.final_metrics["action_accuracy"], abs=1e-9)
    figures = paired_hits(a, b, resamples=100)
    assert figures["diff"] == pytest.approx(b.accuracy - a.accuracy)


def test_a_grounding_stage_run_is_refused_in_one_line(reference_run, tmp_path):
    out, _ = reference_run
    config = json.loads((out / "train_config.json").read_text())
    config["stage"] = "grounding"
    (tmp_path / "train_config.json").write_text(json.dumps(config))
    done = run_group(
        [sys.executable, str(SCRIPT), "--run", f"a={tmp_path}", "--run", f"b={out}"], timeout=300
    )
    assert done.returncode == 1 and done.stderr.strip().endswith("it predicts no actions")
    assert len(done.stderr.strip().splitlines()) == 1


def test_each_step_keeps_its_own_hit_whatever_the_batching(reference_run):
    from bench.analysis.offline_compare import collect_step_hits

    out, _ = reference_run
    one_by_one = collect_step_hits(out, max_samples=None, batch_size=1)  # one sample per forward: no mapping
    batched = collect_step_hits(out, max_samples=None, batch_size=5)
    assert 0 < one_by_one.hits.sum() < len(one_by_one.hits)  # both outcomes occur, so an order mix-up shows
    assert batched.keys == one_by_one.keys and batched.hits.tolist() == one_by_one.hits.tolist()

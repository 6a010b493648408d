"""Stage chaining: a grounding stage on referring expressions, then a navigation stage that starts from it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
from conftest import built_agent, checkpoint_weights, make_config, train_in_process
from safetensors.torch import save_file

from openfly_agent.toolchain.config import GroundingDataConfig
from openfly_agent.toolchain.grounding import generate_grounding
from openfly_agent.training.init_matching import load_matching_weights
from openfly_agent.training.preflight import PreflightError
from openfly_agent.utils.processes import run_group


@pytest.fixture(scope="module")
def grounding_root(generated_dataset, tmp_path_factory):
    root = tmp_path_factory.mktemp("grounding") / "g"
    generate_grounding(
        GroundingDataConfig(source_root=str(generated_dataset), output_dir=str(root), yaw_copies=0)
    )
    return root


@pytest.fixture(scope="module")
def grounding_run(generated_dataset, grounding_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("grounding_stage")
    cfg = make_config(
        generated_dataset, out, stage="grounding", data__grounding_root=str(grounding_root),
        freeze_stage="full", model__action_head__box_token="false",
    )  # fmt: skip
    return out, train_in_process(cfg)


def test_grounding_stage_trains_on_expressions_and_reports_target_iou(grounding_run):
    out, result = grounding_run
    assert result.state.step == 4
    final = result.final_metrics
    assert "action_accuracy" not in final and "majority_class_rate" not in final  # no action targets
    assert 0.0 <= final["box_iou"] <= 1.0 and final["samples"] == 8
    records = [json.loads(line) for line in (out / "logs" / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in records if "train/grounding_loss" in r]
    assert train and all(r["train/grounding_loss"] > 0 for r in train)


def test_navigation_stage_loads_the_matching_weights_and_lists_the_new_ones(
    generated_dataset, grounding_run, tmp_path, caplog
):
    grounding_dir, _ = grounding_run
    cfg = make_config(
        generated_dataset, tmp_path, init__checkpoint=str(grounding_dir), init__matching="true",
        freeze_stage="full", steps=1,
    )  # fmt: skip
    with caplog.at_level("INFO", logger="openfly_agent.training.builder"):
        agent = built_agent(cfg)
    line = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("initialised from"))
    assert "new 4 [box_token_embed.fc1.bias" in line and "other shape 0" in line and "unused 0" in line
    before = checkpoint_weights(grounding_dir / "checkpoints" / "step-000004")
    after = agent.network.state_dict()  # the released names, as the checkpoint has them
    assert {k for k in after if k not in before} == {k for k in after if k.startswith("box_token_embed.")}
    for key, tensor in before.items():  # every tensor of the grounding stage, the embeddings included
        torch.testing.assert_close(after[key], tensor, rtol=0, atol=0, msg=key)
    assert (grounding_dir / "tokenizer").is_dir() and not (tmp_path / "tokenizer").exists()  # its tokenizer


def test_grounding_stage_without_a_root_is_refused(generated_dataset, tmp_path):
    from openfly_agent.training.config import TrainConfig

    cfg = make_config(generated_dataset, tmp_path)
    with pytest.raises(ValueError, match="data.grounding_root"):
        TrainConfig(**{**vars(cfg), "stage": "grounding"})


def test_matching_loads_name_and_shape_matches_only(tmp_path):
    saved = torch.nn.ModuleDict(
        {"a": torch.nn.Linear(3, 4), "b": torch.nn.Linear(2, 2), "old": torch.nn.Linear(1, 1)}
    )
    folder = tmp_path / "ckpt"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    save_file({k: v.contiguous() for k, v in saved.state_dict().items()}, str(folder / "model.safetensors"))
    model = torch.nn.ModuleDict(
        {"a": torch.nn.Linear(3, 4), "b": torch.nn.Linear(2, 3), "new": torch.nn.Linear(1, 1)}
    )
    b_before = model["b"].weight.detach().clone()
    report = load_matching_weights(model, folder)
    assert report.loaded == ["a.bias", "a.weight"]
    assert report.reshaped == ["b.bias", "b.weight"] and report.unused == ["old.bias", "old.weight"]
    assert report.new == ["new.bias", "new.weight"]
    assert torch.equal(model["a"].weight, saved["a"].weight) and torch.equal(model["b"].weight, b_before)
    assert "loaded 2 tensors; new 2 [new.bias, new.weight]" in report.summary()


def test_matching_refuses_a_missing_checkpoint(generated_dataset, tmp_path):
    cfg = make_config(
        generated_dataset, tmp_path, init__checkpoint=str(tmp_path / "nope"), init__matching="true"
    )
    with pytest.raises(PreflightError, match="does not exist"):
        train_in_process(cfg)


def test_grounding_errors_of_a_run_match_its_own_test_iou(grounding_run, tmp_path):
    out, result = grounding_run
    report = tmp_path / "errors.json"
    script = Path(__file__).resolve().parents[2] / "bench" / "grounding_errors.py"
    done = run_group(
        [sys.executable, str(script), "--run", str(out), "--max_samples", "8", "--batch_size", "3",
         "--threads", "1", "--json", str(report)],
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    errors = json.loads(report.read_text())
    assert errors["samples"] == result.final_metrics["samples"] == 8  # the run's test subset (evenly spaced)
    # the same checkpoint on the same samples: the breakdown's mean is the run's own test IoU
    assert errors["mean_iou"] == pytest.approx(result.final_metrics["box_iou"], abs=1e-5)
    assert sum(entry["count"] for entry in errors["by_area"]) == errors["count"] > 0
    assert sum(entry["count"] for entry in errors["by_offset"]) == errors["count"]
    assert "| mean IoU |" in done.stdout


def test_grounding_errors_decode_with_the_centre_window_asked_for(grounding_run):
    from bench.analysis.grounding_errors import collect_target_boxes

    out, _ = grounding_run
    every = collect_target_boxes(out, max_samples=8, batch_size=4, centre_window=None)
    best_cell = collect_target_boxes(out, max_samples=8, batch_size=4, centre_window=0)
    assert len(every.target) > 0
    assert torch.equal(every.cell_logits, best_cell.cell_logits)  # the same scores, decoded two ways
    assert not torch.equal(every.pred, best_cell.pred)


def test_grounding_errors_read_the_split_of_another_dataset_root_when_asked(
    grounding_run, generated_dataset, tmp_path
):
    from bench.analysis.grounding_errors import collect_target_boxes

    out, _ = grounding_run
    own = collect_target_boxes(out, max_samples=8, batch_size=4)
    same = collect_target_boxes(out, max_samples=8, batch_size=4, data_root=generated_dataset)
    assert torch.equal(own.pred, same.pred) and torch.equal(own.target, same.target)
    with pytest.raises(PreflightError, match=str(tmp_path / "elsewhere")):
        collect_target_boxes(out, max_samples=8, data_root=tmp_path / "elsewhere")


def test_grounding_errors_refuse_a_folder_that_is_not_a_run(tmp_path):
    from bench.analysis.grounding_errors import collect_target_boxes

    with pytest.raises(FileNotFoundError, match="not a training run"):
        collect_target_boxes(tmp_path)


def test_grounding_stage_trains_the_attribute_term(generated_dataset, grounding_root, tmp_path):
    cfg = make_config(
        generated_dataset, tmp_path, stage="grounding", data__grounding_root=str(grounding_root),
        freeze_stage="full", model__action_head__box_token="false", model__grounding__attribute_weight="1.0",
    )  # fmt: skip
    assert train_in_process(cfg).state.step == 4
    records = [json.loads(line) for line in (tmp_path / "logs" / "metrics.jsonl").read_text().splitlines()]
    terms = [r["train/attribute_loss"] for r in records if "train/attribute_loss" in r]
    assert terms and all(value >= 0 for value in terms) and max(terms) > 0


def test_grounding_step_bench_times_the_stage_and_counts_its_padding(
    generated_dataset, grounding_root, tmp_path
):
    import importlib

    bench = importlib.import_module("bench.grounding_step")
    threads = torch.get_num_threads()
    overrides = [
        f"--data.root={generated_dataset}", f"--data.grounding_root={grounding_root}", f"--output_dir={tmp_path}",
        "--batch.global_batch_size=4", "--batch.per_device_batch_size=4",
        "--model.llm.length_groups=2",
    ]  # fmt: skip
    record = bench.main(["--steps", "2", "--warmup", "1", "--threads", "1", "--", *overrides])
    assert record["ms_per_micro_step"] > 0 and record["micro_batch_rows"] >= 4
    assert 0 < record["attended_tokens"] <= record["padded_tokens"]
    assert record["overrides"] == overrides
    assert torch.get_num_threads() == threads  # restored for the in-process runs that follow


def test_the_progress_bar_shows_only_the_metrics_a_step_has():
    from openfly_agent.training.after_step import progress_postfix

    grounding = {"loss": 0.51234, "grounding_loss": 0.5, "box_iou": 0.25}  # no action targets
    assert progress_postfix(grounding) == {"loss": "0.5123"}
    navigation = {"loss": 1.0, "action_accuracy": 0.4567}
    assert progress_postfix(navigation) == {"loss": "1.0000", "acc": "0.457"}
    assert progress_postfix({"loss": float("nan")}) == {}


def as_written_at_505bc83(agent: dict) -> dict:
    """A tiny model's `agent` section of config.json as commit 505bc83 wrote it, before issue 46: the LLM a
    `preset` with its sizes filled in, the memory encoding a top-level `mode`, the grounding head a boolean."""
    old = json.loads(json.dumps(agent))
    old["llm"]["preset"] = old["llm"].pop("type")
    old["mode"] = "openfly"
    del old["memory"]["encoding"]
    old["grounding"]["enabled"] = True
    old["action_head"]["n_bins"] = 256
    return old


def test_a_checkpoint_written_before_the_config_variants_starts_a_run(
    generated_dataset, reference_run, tmp_path
):
    # init.checkpoint without init.matching compares the stored config with the configured model: an older
    # config.json is read as loading reads it (upgraded), not refused as "another architecture"
    import shutil

    old = tmp_path / "old"
    shutil.copytree(reference_run[0] / "checkpoints" / "last", old)
    stored = json.loads((old / "config.json").read_text())
    stored["agent"] = as_written_at_505bc83(stored["agent"])
    (old / "config.json").write_text(json.dumps(stored))
    agent = built_agent(make_config(generated_dataset, tmp_path / "run", init__checkpoint=str(old), steps=1))
    before = checkpoint_weights(old)
    for key, tensor in agent.network.state_dict().items():
        torch.testing.assert_close(tensor, before[key], rtol=0, atol=0, msg=key)

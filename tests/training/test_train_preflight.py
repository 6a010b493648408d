"""Preflight errors, raised before any compute: output folder, batch sizes, dataset, checkpoint shapes."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import save_file

from openfly_agent import constants as C
from openfly_agent.data.config import DataConfig, ReaderOptions
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import BatchConfig, BatchSizeError
from openfly_agent.training.preflight import (
    PreflightError,
    check_batch,
    check_dataset_root,
    check_output_dir,
    checkpoint_tensor_shapes,
    compare_shapes,
    diff_configs,
    load_split,
    resolve_val_split,
)


def test_fresh_output_dir_is_created(tmp_path):
    assert check_output_dir(tmp_path / "a" / "b", resume=False) is None
    assert (tmp_path / "a" / "b").is_dir()


def test_unwritable_output_dir(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")  # a folder cannot be created under a file, even by root
    with pytest.raises(PreflightError, match="is not writable"):
        check_output_dir(blocker / "run", resume=False)


def test_output_dir_with_checkpoints_needs_resume(tmp_path):
    manager = CheckpointManager(tmp_path, keep_last=2)
    manager.begin(4)
    manager.commit(4)
    with pytest.raises(PreflightError, match="--resume=true"):
        check_output_dir(tmp_path, resume=False)
    assert check_output_dir(tmp_path, resume=True) == tmp_path / "checkpoints" / "step-000004"
    with pytest.raises(PreflightError, match="holds no complete checkpoint"):
        check_output_dir(tmp_path / "other", resume=True)


def test_batch_sizes_must_divide():
    assert check_batch(BatchConfig(global_batch_size=16, per_device_batch_size=4), world_size=2) == 2
    with pytest.raises(
        PreflightError, match=r"does not divide by per_device_batch_size \(4\) x processes \(3\)"
    ):
        check_batch(BatchConfig(global_batch_size=16, per_device_batch_size=4), world_size=3)
    with pytest.raises(BatchSizeError, match="not a positive multiple"):
        BatchConfig(global_batch_size=10, per_device_batch_size=4)


def test_missing_dataset_root_says_how_to_generate_it_or_get_the_released_data(tmp_path):
    data = DataConfig(root=str(tmp_path / "nowhere"))
    with pytest.raises(PreflightError) as err:
        check_dataset_root(data)
    assert f"python -m openfly_agent.toolchain generate --output_dir={tmp_path / 'nowhere'}" in str(err.value)
    assert "data_cards/openfly_released.md" in str(err.value)


def test_missing_split_is_named(tmp_path, openfly_fixtures):
    annotation = tmp_path / C.DATASET_ANNOTATION_DIR
    annotation.mkdir()
    records = json.loads((openfly_fixtures / "eval_test.json").read_text())[:3]
    (annotation / "train.json").write_text(json.dumps(records))
    with pytest.raises(PreflightError, match="no annotation for split 'test_seen'"):
        check_dataset_root(resolve_val_split(DataConfig(root=str(tmp_path)))[0])  # train()'s order


def test_validation_falls_back_to_test_seen_only_on_a_dataset_without_a_val_split(tmp_path, openfly_fixtures):
    annotation = tmp_path / C.DATASET_ANNOTATION_DIR
    annotation.mkdir()
    records = json.loads((openfly_fixtures / "eval_test.json").read_text())[:3]
    for name in ("train.json", "seen.json", "unseen.json"):  # the released data's files
        (annotation / name).write_text(json.dumps(records))
    data = DataConfig(root=str(tmp_path))
    assert data.val_split == C.SPLIT_VAL
    resolved, warning = resolve_val_split(data)
    assert resolved.val_split == C.SPLIT_TEST_SEEN
    assert "has no val split" in warning and "validating on test_seen" in warning
    (annotation / "val.json").write_text("[]")  # a dataset generated without val units
    assert resolve_val_split(data)[0].val_split == C.SPLIT_TEST_SEEN
    (annotation / "val.json").write_text(json.dumps(records[:1]))
    assert resolve_val_split(data) == (data, None)  # a val split: used, no warning
    explicit = DataConfig(root=str(tmp_path), val_split=C.SPLIT_TRAIN)
    assert resolve_val_split(explicit) == (explicit, None)  # an explicit choice is kept
    missing = DataConfig(root=str(tmp_path / "nowhere"))
    assert resolve_val_split(missing) == (missing, None)  # check_dataset_root names the missing root


def test_malformed_record_names_file_record_and_field(tmp_path, openfly_fixtures):
    annotation = tmp_path / C.DATASET_ANNOTATION_DIR
    annotation.mkdir()
    records = json.loads((openfly_fixtures / "eval_test.json").read_text())[:3]
    records[2]["yaw"] = records[2]["yaw"][:-1]  # one yaw short
    (annotation / "train.json").write_text(json.dumps(records))
    with pytest.raises(PreflightError) as err:
        load_split(DataConfig(root=str(tmp_path)), C.SPLIT_TRAIN)
    message = str(err.value)
    assert "train.json" in message and "yaw" in message and "2" in message
    # strict (the default) names the option that skips such records; non-strict skips it
    assert message.endswith("--data.reader.strict=false skips each one, logged and counted)")
    data = DataConfig(root=str(tmp_path), reader=ReaderOptions(strict=False))
    assert len(load_split(data, C.SPLIT_TRAIN)) == 2


def test_checkpoint_shapes_from_headers_and_mismatch_report(tmp_path):
    save_file({"a.weight": torch.zeros(4, 3), "b.bias": torch.zeros(2)}, str(tmp_path / C.WEIGHTS_NAME))
    found = checkpoint_tensor_shapes(tmp_path)
    assert found == {"a.weight": (4, 3), "b.bias": (2,)}
    compare_shapes({"a.weight": (4, 3), "b.bias": (2,)}, found, "ckpt")
    with pytest.raises(PreflightError) as err:
        compare_shapes({"a.weight": (8, 3), "c.weight": (1,)}, found, "ckpt")
    message = str(err.value)
    assert "a.weight (4, 3) vs (8, 3)" in message and "missing (1): ['c.weight']" in message
    assert "unexpected (1): ['b.bias']" in message
    with pytest.raises(PreflightError, match="neither"):
        checkpoint_tensor_shapes(tmp_path / "empty")


def test_diff_configs_lists_dotted_paths():
    lines = diff_configs(
        {"llm": {"hidden_size": 128, "layers": 2}}, {"llm": {"hidden_size": 64, "layers": 2}}
    )
    assert lines == ["model.llm.hidden_size: checkpoint 64, config 128"]

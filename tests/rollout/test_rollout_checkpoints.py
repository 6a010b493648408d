"""Checkpoints as agents: a checkpoint folder, a training run, its `checkpoints/` folder or pointer resolve to the
newest checkpoint; the fingerprint follows the weights."""

from __future__ import annotations

import pytest

from openfly_agent.rollout.checkpoints import (
    checkpoint_fingerprint,
    checkpoint_folder,
    checkpoint_kind,
    describe_weights_change,
)


def test_training_run_paths_resolve_to_the_newest_checkpoint(tmp_path):
    step = tmp_path / "run" / "checkpoints" / "step-000010"
    step.mkdir(parents=True)
    (step / "config.json").write_text('{"model_type": "openfly_agent"}')
    (tmp_path / "run" / "checkpoints" / "last").write_text("step-000010\n")
    for path in ("run", "run/checkpoints", "run/checkpoints/last", "run/checkpoints/step-000010"):
        assert checkpoint_folder(str(tmp_path / path)) == step
    assert checkpoint_kind(step) == "openfly_agent"
    with pytest.raises(FileNotFoundError, match="no config.json"):
        checkpoint_folder(str(tmp_path))
    (step / "config.json").write_text('{"model_type": "llama"}')
    with pytest.raises(ValueError, match="model_type 'llama'"):
        checkpoint_kind(step)


def test_fingerprint_follows_the_newest_weights(tmp_path):
    checkpoints = tmp_path / "run" / "checkpoints"
    for name in ("step-000010", "step-000020"):
        (checkpoints / name).mkdir(parents=True)
        (checkpoints / name / "config.json").write_text('{"model_type": "openfly_agent"}')
        (checkpoints / name / "model.safetensors").write_bytes(b"x" * len(name))
    (checkpoints / "last").write_text("step-000010")
    before = checkpoint_fingerprint(str(tmp_path / "run"))
    assert before["folder"].endswith("step-000010") and list(before["weights"]) == ["model.safetensors"]
    (checkpoints / "last").write_text("step-000020")  # the run trained on: same --checkpoint, new weights
    assert checkpoint_fingerprint(str(tmp_path / "run")) != before


def test_weights_change_is_said_in_words():
    second = 1_795_770_896 * 10**9  # 2026-11-27 09:14:56 UTC
    old = {"folder": "/r/step-4", "weights": {"model.safetensors": [1234, second]}}
    resaved = {"folder": "/r/step-4", "weights": {"model.safetensors": [1234, second + 250_000_000]}}
    # within one second: the milliseconds tell the two writes apart
    assert describe_weights_change(old, resaved) == (
        "/r/step-4: model.safetensors was written again: 1,234 B modified 2026-11-27 09:14:56.000 UTC then, "
        "1,234 B modified 2026-11-27 09:14:56.250 UTC now"
    )
    other = {"folder": "/r/step-8", "weights": {"model.safetensors": [99, second]}}
    assert describe_weights_change(old, other) == (
        "/r/step-4 (model.safetensors 1,234 B modified 2026-11-27 09:14:56 UTC) -> "
        "/r/step-8 (model.safetensors 99 B modified 2026-11-27 09:14:56 UTC)"
    )
    gone = {"folder": "/r/step-4", "weights": {}}
    assert describe_weights_change(old, gone) == (
        "/r/step-4: model.safetensors is gone (it was 1,234 B modified 2026-11-27 09:14:56 UTC)"
    )


def test_a_released_folder_that_does_not_fit_the_model_config_is_one_line_naming_eval_option(tmp_path):
    """eval.py on a reduced-width OpenVLA folder with the default (7B) released model config: a CheckpointError
    (one line, exit 2 in eval.py) that names the sizes and the option that gives the right config, read from the
    headers before any 7B weight is allocated."""
    import importlib

    from openfly_agent.rollout.checkpoints import CheckpointError, load_agent

    folder = tmp_path / "openvla"
    importlib.import_module("bench.synthetic_openvla").write_synthetic_openvla(folder, "reduced")
    with pytest.raises(CheckpointError) as info:
        load_agent(str(folder))
    message = str(info.value)
    assert "\n" not in message
    assert "checkpoint llm hidden size 128, config 4096" in message
    assert message.endswith(
        "(the ModelConfig YAML of a released folder: eval.py --agent.model_config=<file>; now the 7B "
        "openvla_compat preset)"
    )

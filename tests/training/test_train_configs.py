"""Every shipped train / accelerate config parses, and the config checks reject what they should."""

from __future__ import annotations

from pathlib import Path

import pytest
from accelerate.commands.config.config_args import load_config_from_file

from openfly_agent.data.config import DataConfig
from openfly_agent.training.accelerator import flat_config
from openfly_agent.training.config import BatchConfig, BatchSizeError, OptimConfig, TrainConfig
from openfly_agent.utils.config import config_from_dict, config_to_dict, parse_config
from openfly_agent.utils.errors import root_cause

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
TRAIN_CONFIGS = sorted((CONFIGS / "train").glob("*.yaml")) + sorted(
    (CONFIGS / "train" / "ablations").glob("*.yaml")
)


@pytest.mark.parametrize("path", TRAIN_CONFIGS, ids=lambda p: p.stem)
def test_train_config_parses_and_round_trips(path):
    cfg = parse_config(TrainConfig, [], config_path=path)
    assert config_from_dict(TrainConfig, config_to_dict(cfg)) == cfg
    assert all(isinstance(v, (str, int, float, bool)) for v in flat_config(cfg).values())


def test_ablations_match_the_paper_table():
    expected = {  # history mode, memory sets K, token merging
        "current_frame": ("none", 0, False),
        "uniform_history": ("uniform", 2, False),
        "random_keyframes": ("random", 2, False),
        "keyframes": ("keyframes", 2, False),
        "uniform_history_merging": ("uniform", 2, True),
        "keyframes_merging": ("keyframes", 2, True),
    }
    found = {}
    for path in sorted((CONFIGS / "train" / "ablations").glob("*.yaml")):
        cfg = parse_config(TrainConfig, [], config_path=path)
        found[path.stem] = (cfg.data.history.mode, cfg.model.memory.capacity, cfg.model.merging.enabled)
        assert cfg.output_dir.endswith(path.stem.replace("_", "-"))
    assert found == expected


def test_paper_recipe_values():
    cfg = parse_config(TrainConfig, [], config_path=CONFIGS / "train" / "openfly-7b-full.yaml")
    assert (cfg.optim.lr, cfg.optim.schedule, cfg.optim.weight_decay, cfg.optim.max_grad_norm) == (
        2e-5,
        "constant",
        0.0,
        1.0,
    )
    assert (cfg.batch.global_batch_size, cfg.precision, cfg.model.llm.type) == (128, "bf16", "llama2-7b")
    lora = parse_config(TrainConfig, [], config_path=CONFIGS / "train" / "openfly-7b-lora.yaml")
    assert lora.use_lora and lora.freeze_stage == "lora" and lora.lora.rank == 32
    assert not cfg.use_lora


@pytest.mark.parametrize("name", ["openfly-7b-lora.yaml", "openfly-7b-full.yaml"])
def test_the_7b_configs_read_the_released_data_as_its_config_says(name):
    """The README's 7B commands read the release non-strictly (it has a few malformed records), with the data
    section of configs/data/openfly_released.yaml itself, not a copy of it."""
    cfg = parse_config(TrainConfig, [], config_path=CONFIGS / "train" / name)
    released = parse_config(DataConfig, [], config_path=CONFIGS / "data" / "openfly_released.yaml")
    assert cfg.data == released
    assert cfg.data.reader.strict is False


def test_a_section_file_lays_its_keys_over_the_config_and_options_still_win():
    """`--model=configs/model/reduced-width.yaml`: the file's keys replace those of the 7B model section, the keys
    it does not name keep the 7B values, and a dotted option wins wherever it stands; it is bench's reduced width."""
    import importlib

    lora = str(CONFIGS / "train" / "openfly-7b-lora.yaml")
    file = "configs/model/reduced-width.yaml"
    for argv in (
        [f"--model={file}", "--model.memory.grid=2"],
        ["--model.memory.grid=2", "--model", file],
    ):
        model = parse_config(TrainConfig, ["--config_path", lora, *argv]).model
        assert (model.vision.type, model.vision.image_size, model.vision.patch_size) == ("tiny", 56, 14)
        assert (model.llm.type, model.memory.grid) == ("tiny", 2)
        assert (model.llm.vocab_size, model.llm.pad_token_id, model.grounding.type) == (32064, 32000, "box")
    reduced = parse_config(TrainConfig, ["--config_path", lora, f"--model={file}"]).model
    assert reduced == importlib.import_module("bench.synthetic_openvla").model_config("reduced")


def test_command_line_overrides_the_yaml():
    cfg = parse_config(
        TrainConfig,
        ["--optim.lr=0.5", "--data.history.mode=random"],
        config_path=CONFIGS / "train" / "tiny.yaml",
    )
    assert cfg.optim.lr == 0.5 and cfg.data.history.mode == "random"


@pytest.mark.parametrize("path", sorted((CONFIGS / "accelerate").glob("*.yaml")), ids=lambda p: p.stem)
def test_accelerate_config_loads(path):
    cluster = load_config_from_file(str(path))
    assert cluster.num_processes >= 1


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"precision": "fp8"}, "precision='fp8'"),
        ({"steps": None, "epochs": None}, "set `steps`"),
        ({"data": {"history": {"mode": "latest"}}}, "data.history.mode='latest'"),
        (
            {"model": {"llm": {"type": "llama2-7b", "hidden_size": 64}}},
            "`hidden_size`, `num_layers`, `num_heads`, `intermediate_size` are not valid for Llama2LLMConfig",
        ),
        ({"optim": {"schedule": "step"}}, "optim.schedule='step'"),
    ],
)
def test_bad_values_are_rejected_with_the_field_named(changes, message):
    data = config_to_dict(TrainConfig())
    for key, value in changes.items():
        if isinstance(value, dict):
            for sub, subvalue in value.items():
                if isinstance(subvalue, dict):
                    data[key][sub].update(subvalue)
                else:
                    data[key][sub] = subvalue
        else:
            data[key] = value
    with pytest.raises(Exception) as err:
        config_from_dict(TrainConfig, data)
    assert message in root_cause(err.value)


def test_batch_config_rejects_non_multiple():
    with pytest.raises(Exception) as err:
        parse_config(TrainConfig, ["--batch.global_batch_size=12", "--batch.per_device_batch_size=8"])
    assert "not a positive multiple" in root_cause(err.value)
    with pytest.raises(BatchSizeError):
        BatchConfig(global_batch_size=12, per_device_batch_size=8)
    with pytest.raises(ValueError, match="optim.lr"):
        OptimConfig(lr=0.0)


def test_a_time_horizon_needs_a_time_limit():
    with pytest.raises(ValueError, match="time_limit_minutes"):
        TrainConfig(optim=OptimConfig(horizon="time"))
    assert TrainConfig(optim=OptimConfig(horizon="time"), time_limit_minutes=5.0).optim.horizon == "time"
    with pytest.raises(ValueError, match="optim.horizon"):
        OptimConfig(horizon="epochs")

"""configs/accelerate/*.yaml: accelerate 1.15 reads every file and knows every option it names, and the FSDP files
give the plugin train.py's preflight reads (sharding, CPU offload, activation checkpointing)."""

from __future__ import annotations

import pytest
from conftest import REPO_ROOT

ACCELERATE_CONFIGS = sorted((REPO_ROOT / "configs" / "accelerate").glob("*.yaml"))
# how `accelerate launch` maps a nested section's keys to its own options (accelerate/commands/launch.py)
PREFIXES = {"fsdp_config": "fsdp_", "dynamo_config": "dynamo_", "deepspeed_config": ""}


def launch_options() -> set[str]:
    from accelerate.commands.launch import launch_command_parser

    return {action.dest for action in launch_command_parser()._actions}


def test_the_shipped_files():
    names = {path.name for path in ACCELERATE_CONFIGS}
    assert {"cpu.yaml", "single_gpu.yaml", "fsdp.yaml", "fsdp_offload.yaml"} <= names


def unknown_options(path) -> list[str]:
    """The nested options of an accelerate config file that `accelerate launch` would silently ignore (unknown
    top-level keys already raise in accelerate's own loader)."""
    from accelerate.commands.config.config_args import load_config_from_file

    config = load_config_from_file(str(path))
    known = launch_options()
    unknown = []
    for section, prefix in PREFIXES.items():
        for key in getattr(config, section, None) or {}:
            if (key if key.startswith(prefix) else prefix + key) not in known:
                unknown.append(f"{section}.{key}")
    return unknown


@pytest.mark.parametrize("path", ACCELERATE_CONFIGS, ids=lambda p: p.name)
def test_accelerate_reads_the_file_and_knows_each_option(path):
    assert unknown_options(path) == []


def test_a_misspelt_option_is_caught(tmp_path):
    text = (REPO_ROOT / "configs/accelerate/fsdp_offload.yaml").read_text()
    path = tmp_path / "typo.yaml"
    path.write_text(text.replace("fsdp_offload_params:", "fsdp_ofload_params:"))
    assert unknown_options(path) == ["fsdp_config.fsdp_ofload_params"]
    path.write_text(text.replace("num_machines:", "num_machine:"))
    with pytest.raises(ValueError, match="unknown keys"):
        unknown_options(path)


def _free_port() -> int:
    """A TCP port nothing listens on now (the OS picks it)."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize(
    ("name", "offload"), [("fsdp.yaml", False), ("fsdp_offload.yaml", True), ("fsdp_multinode.yaml", False)]
)
def test_fsdp_files_give_the_plugin_the_preflight_reads(name, offload, monkeypatch):
    """`accelerate launch --config_file <name>`'s environment, then the plugin the Accelerator would build."""
    from accelerate.commands.launch import _validate_launch_command, launch_command_parser
    from accelerate.utils import FullyShardedDataParallelPlugin
    from accelerate.utils.launch import prepare_multi_gpu_env
    from timm.models.vision_transformer import Block
    from transformers.models.llama.modeling_llama import LlamaDecoderLayer

    from openfly_agent.training.memory_estimate import SHARDING_FSDP, Sharding, fsdp_sharding

    args = launch_command_parser().parse_args(
        ["--config_file", str(REPO_ROOT / "configs/accelerate" / name), "x"]
    )
    args, _, _ = _validate_launch_command(args)
    # a free port: accelerate refuses one in use, e.g. by a 2-process training run beside the suite (29500)
    args.main_process_port = _free_port()
    for key, value in prepare_multi_gpu_env(args).items():
        monkeypatch.setenv(key, value)
    plugin = FullyShardedDataParallelPlugin()
    assert plugin.fsdp_version == 2
    assert set(plugin.transformer_cls_names_to_wrap) == {LlamaDecoderLayer.__name__, Block.__name__}
    world = args.num_processes
    assert fsdp_sharding(plugin, world) == Sharding(
        SHARDING_FSDP, world, offload, activation_checkpointing=True
    )

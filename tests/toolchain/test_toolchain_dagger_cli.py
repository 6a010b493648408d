"""`dagger` and `dagger-round` read the agent's `checkpoint` (and `dagger-round` its `torch_threads`) as fields of
their typed config: shown in `--help`, checked with every other field, and left out of the settings a dataset
records."""

from __future__ import annotations

import sys
from pathlib import Path

from openfly_agent.toolchain.__main__ import (
    DaggerCommandConfig,
    DaggerRoundCommandConfig,
    _as_base,
    _generate_args,
    _parse_generate,
)
from openfly_agent.toolchain.config import DaggerRoundConfig, GenerateConfig
from openfly_agent.utils.config import config_to_dict, parse_config
from openfly_agent.utils.processes import run_group

REPO = Path(__file__).resolve().parents[2]


def _help(command: str) -> str:
    done = run_group(
        [sys.executable, "-m", "openfly_agent.toolchain", command, "--help"], timeout=120, cwd=REPO
    )
    assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
    return " ".join(done.stdout.split())


def test_the_dagger_commands_show_checkpoint_and_torch_threads_in_help():
    dagger, round_help = _help("dagger"), _help("dagger-round")
    assert (
        "--checkpoint STR trained agent folder (or Hub id) that flies the DAgger episodes (required)"
        in dagger
    )
    assert (
        "--checkpoint STR trained agent folder (or Hub id) that flies the rollouts (required)" in round_help
    )
    assert "--torch_threads INT torch threads of the rollouts (0: torch's default) (default: 0)" in round_help


def test_the_command_fields_are_parsed_and_left_out_of_the_recorded_settings():
    cfg = parse_config(
        DaggerRoundCommandConfig, ["--checkpoint", "runs/nav", "--torch_threads=3", "--episodes=5"]
    )
    assert (cfg.checkpoint, cfg.torch_threads, cfg.episodes) == ("runs/nav", 3, 5)
    round_cfg = _as_base(cfg, DaggerRoundConfig)
    assert type(round_cfg) is DaggerRoundConfig and round_cfg == DaggerRoundConfig(episodes=5)
    dagger = parse_config(DaggerCommandConfig, _generate_args(["--checkpoint=runs/nav", "--render.width=96"]))
    settings = _as_base(dagger, GenerateConfig)
    assert type(settings) is GenerateConfig and dagger.checkpoint == "runs/nav"
    # the settings the dataset records are those of `generate` with the same options
    assert config_to_dict(settings) == config_to_dict(_parse_generate(["--render.width=96"]))

"""Every entry point, typed as a user types it: a bad value or a missing file is exactly one line on stderr and
exit code 2, and the command leaves nothing behind in the working directory. All of these fail while the command
line is parsed, before any model, simulator or dataset is touched."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from openfly_agent.utils.processes import run_group

REPO = Path(__file__).resolve().parents[1]
TOOLCHAIN = ["-m", "openfly_agent.toolchain"]
CASES = {  # id: (command after `python`, what the one line must hold)
    "train: a registered choice that names no variant": (
        [str(REPO / "train.py"), "--model.vision.type=resnet"],
        "train.py: --model.vision.type: unknown choice 'resnet'; choose one of tiny-cnn, tiny, dinosiglip-224px",
    ),
    "train: the LLM, a registered choice, named wrong": (
        [str(REPO / "train.py"), "--model.llm.type=llama3"],
        "train.py: --model.llm.type: unknown choice 'llama3'; choose one of tiny, llama2-7b",
    ),
    "train: a memory encoding that names no variant": (
        [str(REPO / "train.py"), "--model.memory.encoding.type=uniform"],
        "train.py: --model.memory.encoding.type: unknown choice 'uniform'; choose one of keyframes, openvla_history",
    ),
    "train: a missing --config_path": (
        [str(REPO / "train.py"), "--config_path", "configs/train/tinny.yaml"],
        "train.py: --config_path configs/train/tinny.yaml: no such file",
    ),
    "eval: a registered choice that names no variant": (
        [str(REPO / "eval.py"), "--sim.type=habitat"],
        "eval.py: --sim.type: unknown choice 'habitat'; choose one of embedded, unrealcv, airsim, gs_http",
    ),
    "eval: a list without brackets": (
        [str(REPO / "eval.py"), "--split=test_unseen"],
        "eval.py: --split takes a list, written in brackets: --split=[test_unseen]",
    ),
    "eval: a missing --config_path": (
        [str(REPO / "eval.py"), "--config_path=missing.yaml"],
        "eval.py: --config_path missing.yaml: no such file",
    ),
    "toolchain: no command": (TOOLCHAIN, "no command given; choose one of generate, summarize"),
    "toolchain generate: a missing --config_path": (
        [*TOOLCHAIN, "generate", "--config_path=missing.yaml"],
        "toolchain generate: --config_path missing.yaml: no such file",
    ),
    "toolchain generate: a negative city seed": (
        [*TOOLCHAIN, "generate", "--scenes.train_seeds=[-1]", "--output_dir=data"],
        "scenes.train_seeds: a city seed is an integer >= 0, got -1",
    ),
    "toolchain generate: a seed list without brackets": (
        [*TOOLCHAIN, "generate", "--scenes.unseen_seeds=100", "--output_dir=data"],
        "--scenes.unseen_seeds takes a list, written in brackets: --scenes.unseen_seeds=[100]",
    ),
    "toolchain dagger-round: a value that is no number": (
        [*TOOLCHAIN, "dagger-round", "--checkpoint=run", "--torch_threads=abc"],
        "toolchain dagger-round: bad dagger-round config: --torch_threads: expected an int, got 'abc'",
    ),
    "toolchain dagger-round: a negative thread count": (
        [*TOOLCHAIN, "dagger-round", "--checkpoint=run", "--torch_threads=-1"],
        "toolchain dagger-round: bad dagger-round config: torch_threads must be >= 0 (0: torch's default), got -1",
    ),
    "toolchain dagger: no --checkpoint": (
        [*TOOLCHAIN, "dagger", "--output_dir=data"],
        "toolchain dagger: bad dagger config: --checkpoint is required: the trained agent folder (or Hub id)",
    ),
    "toolchain grounding: a missing --config_path": (
        [*TOOLCHAIN, "grounding", "--config_path=missing.yaml"],
        "toolchain grounding: --config_path missing.yaml: no such file",
    ),
    "recipe: a missing --config_path": (
        ["-m", "openfly_agent.recipe", "--config_path=configs/recipe/main-job.yaml"],
        "python -m openfly_agent.recipe: --config_path configs/recipe/main-job.yaml: no such file",
    ),
    "recipe: a stage override that names no train.py option": (
        ["-m", "openfly_agent.recipe", "--navigation.overrides={optim: {lrr: 1.0}}"],
        "python -m openfly_agent.recipe: navigation.overrides: train.py: unknown option --optim.lrr; did you mean "
        "--optim.lr?",
    ),
    "hub release: a missing --config_path": (
        ["-m", "openfly_agent.hub", "release", "--config_path=missing.yaml"],
        "hub release: --config_path missing.yaml: no such file",
    ),
    "sim.cli render: a list without brackets": (
        ["-m", "openfly_agent.sim.cli", "render", "--pose=1", "--out=frame.png"],
        "sim.cli render: --pose takes a list, written in brackets: --pose=[1]",
    ),
    "sim.cli export: a missing --config_path": (
        ["-m", "openfly_agent.sim.cli", "export", "--config_path=missing.yaml"],
        "sim.cli export: --config_path missing.yaml: no such file",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_value_or_missing_file_is_one_line_and_exit_code_2(case, tmp_path):
    command, expected = CASES[case]
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    done = run_group([sys.executable, *command], timeout=300, cwd=tmp_path, env=env)
    lines = done.stderr.splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr[-3000:]
    assert expected in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []  # no run folder, dataset folder or settings file left behind

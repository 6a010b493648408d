"""The release command line: draccus' dotted options of the config dataclasses (as train.py and eval.py),
defaults kept, errors one line naming the option."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from openfly_agent.hub.cli import main
from openfly_agent.hub.config import CardConfig, DatasetReleaseConfig, ModelReleaseConfig
from openfly_agent.utils.cli_help import field_docs
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.processes import communicate_group, running


def parse_model(argv: list[str]) -> ModelReleaseConfig:
    return parse_config(ModelReleaseConfig, argv)


def test_documented_options_parse_into_the_config():
    cfg = parse_model(
        ["--checkpoint=runs/x", "--repo_id", "me/tiny", "--results=r.json", "--push", "--private=true"]
        + ["--revision=v1", "--lora=adapter", "--card.base_model=me/base", "--card.tags=[a,b]"]
    )
    assert (cfg.checkpoint, cfg.repo_id, cfg.results, cfg.revision, cfg.lora) == (
        "runs/x",
        "me/tiny",
        "r.json",
        "v1",
        "adapter",
    )
    assert cfg.push is True and cfg.private is True
    assert cfg.card.base_model == "me/base" and cfg.card.tags == ["a", "b"]


def test_options_not_given_keep_the_dataclass_defaults():
    cfg = parse_model(["--checkpoint=c", "--repo_id=me/tiny"])
    defaults = ModelReleaseConfig(checkpoint="c", repo_id="me/tiny")
    assert cfg == defaults and cfg.push is False and cfg.card == CardConfig()
    assert parse_model(["--checkpoint=c", "--repo_id=me/t", "--push", "--push=false"]).push is False


def test_dataset_command():
    cfg = parse_config(DatasetReleaseConfig, ["--dataset_root=d", "--repo_id=me/ds", "--push"])
    assert (cfg.dataset_root, cfg.repo_id, cfg.push, cfg.card) == (
        "d",
        "me/ds",
        True,
        "data_cards/embedded.md",
    )


def test_help_comes_from_the_field_comments():
    docs = field_docs(ModelReleaseConfig)
    assert docs["max_shard_size"].startswith("weights above this size are split")
    assert "train_config.json" in docs["base_checkpoint"]  # comment lines above the field are joined
    assert set(docs) == set(ModelReleaseConfig.__dataclass_fields__)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--repo_id=me/tiny"], "--checkpoint is required"),
        (["--checkpoint=c", "--repo_id=tiny"], "namespace/name"),
        (["--checkpoint=c", "--repo_id=me/tiny", "--max_shard_size=big"], "--max_shard_size 'big'"),
        (["--checkpoint=c", "--repo_id=me/tiny", "--revision=has space"], "--revision"),
        (["--checkpoint=c", "--repo-id=me/tiny"], "unknown option --repo-id; did you mean --repo_id?"),
        (["--checkpoint", "--repo_id=me/tiny"], "--checkpoint needs a value: --checkpoint=VALUE"),
        (["--checkpoint=c", "--repo_id=me/tiny", "--card.tags", "a", "b"], "--card.tags takes one value"),
    ],
)
def test_bad_values_exit_with_one_line_naming_the_option(argv, message, capsys):
    assert main(["release", *argv]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("python -m openfly_agent.hub release: ") and message in line


def test_missing_checkpoint_folder_is_named(tmp_path, capsys):
    assert main(["release", f"--checkpoint={tmp_path / 'nope'}", "--repo_id=me/tiny"]) == 2
    assert "is not a checkpoint folder" in capsys.readouterr().err


def _stage_run(root: Path, stage: str) -> Path:
    """A training run of `stage` (config.json + train_config.json, as training writes them) and its `last`."""
    step = root / stage / "checkpoints" / "step-000004"
    step.mkdir(parents=True)
    (step / "config.json").write_text(json.dumps({"model_type": "openfly_agent"}))
    (step / "train_config.json").write_text(json.dumps({"stage": stage, "steps": 4}))
    os.symlink("step-000004", step.parent / "last")
    return root / stage


def test_grounding_stage_checkpoint_is_refused_naming_the_navigation_stage(tmp_path, capsys):
    grounding = _stage_run(tmp_path / "main_job", "grounding")
    _stage_run(tmp_path / "main_job", "navigation")
    out = tmp_path / "release"
    for checkpoint in (grounding, grounding / "checkpoints" / "last"):
        argv = ["release", f"--checkpoint={checkpoint}", "--repo_id=me/x", f"--output_dir={out}"]
        assert main(argv) == 2
        [line] = capsys.readouterr().err.strip().splitlines()
        assert "grounding-stage checkpoint" in line and str(tmp_path / "main_job" / "navigation") in line
    assert not out.exists()  # refused before anything is written


def test_a_truncated_checkpoint_is_one_line_and_makes_no_folder(tmp_path, capsys):
    from eval_helpers import save_small_agent

    folder = tmp_path / "ckpt"
    save_small_agent(folder, ["fly to the red tower"])
    weights = folder / "model.safetensors"
    with open(weights, "r+b") as f:
        f.truncate(weights.stat().st_size // 2)
    capsys.readouterr()  # the save's progress bar
    out = tmp_path / "release"
    argv = ["release", f"--checkpoint={folder}", "--repo_id=me/tiny", f"--output_dir={out}"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        f"python -m openfly_agent.hub release: {weights} is not a readable safetensors file ("
    ), err
    assert not out.exists()


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # how a shell starts a background job


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_fake_hub_command_serves_until_interrupted(tmp_path, stop_signal):
    """It stops and prints its summary on Ctrl-C / SIGTERM, even when started with SIGINT ignored."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    command = [sys.executable, "-m", "openfly_agent.hub", "fake-hub", "--token=tok"]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    with running(command, env=env, preexec_fn=_ignore_sigint, **pipes) as proc:
        try:
            line = proc.stdout.readline()
            url = line.split("HF_ENDPOINT=")[1].split()[0]
            request = urllib.request.Request(
                f"{url}/api/repos/create",
                data=json.dumps({"name": "x", "organization": "me"}).encode(),
                headers={"Authorization": "Bearer tok", "Content-Type": "application/json"},
            )
            assert json.loads(urllib.request.urlopen(request, timeout=10).read())["url"] == f"{url}/me/x"
        finally:
            proc.send_signal(stop_signal)
        out, _ = communicate_group(proc, timeout=30)
    assert proc.returncode == 0 and "model me/x@main: 0 files, 0 bytes" in out

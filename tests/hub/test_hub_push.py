"""Push against a loopback fake Hub (HF_ENDPOINT): files received, private / branch, token never shown."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_hub_dataset import CARD, make_dataset_root  # tests/hub/ is on sys.path (pytest prepend mode)

from openfly_agent.hub.fake_hub import FakeHub
from openfly_agent.hub.push import PushError, push_folder
from openfly_agent.utils.processes import run_group

REPO_ROOT = Path(__file__).resolve().parents[2]
TOKEN = "hf_fakeTokenThatMustNeverBePrinted0123"


def hub_env(hub: FakeHub, home: Path, token: str = TOKEN) -> dict[str, str]:
    """Environment of a release subprocess talking to `hub` (online mode, token in HF_TOKEN only)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGINGFACE_"))}
    env.update(
        HF_ENDPOINT=hub.url,
        HF_TOKEN=token,
        HF_HOME=str(home),
        HF_HUB_OFFLINE="0",
        TRANSFORMERS_OFFLINE="0",
        HF_HUB_DISABLE_TELEMETRY="1",
        OPENFLY_LOG_LEVEL="DEBUG",
        PYTHONPATH=str(REPO_ROOT),
    )
    return env


def run_cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return run_group([sys.executable, "-m", "openfly_agent.hub", *args], timeout=300, env=env, cwd=REPO_ROOT)


def files_containing(folder: Path, needle: str) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and needle.encode() in p.read_bytes()]


def test_dataset_push_uploads_every_file(tmp_path):
    root, _ = make_dataset_root(tmp_path / "data")
    out = tmp_path / "release"
    args = ["release-dataset", "--dataset_root", str(root), "--card", str(CARD), "--output_dir", str(out)]
    args += ["--repo_id", "me/openfly-embedded", "--push", "--private", "--revision", "v0.1"]
    with FakeHub(token=TOKEN) as hub:
        result = run_cli(args, hub_env(hub, tmp_path / "hf_home"))
        assert result.returncode == 0, result.stderr
        received = hub.files("me/openfly-embedded", repo_type="dataset", branch="v0.1")
        repo = hub.repos[("dataset", "me/openfly-embedded")]
    local = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert received == local  # byte-exact, nothing missing, nothing extra
    assert repo.private is True
    assert repo.branches["main"] == {}  # pushed to the requested branch only
    assert [c["summary"] for c in repo.commits] == ["Release OpenFly dataset"]
    assert f"pushed: {hub.url}/datasets/me/openfly-embedded/tree/v0.1" in result.stdout
    assert TOKEN not in result.stdout + result.stderr
    assert not files_containing(tmp_path, TOKEN)  # release folder, dataset, HF_HOME (no login cache written)


def test_wrong_token_fails_cleanly(tmp_path):
    root, _ = make_dataset_root(tmp_path / "data")
    card = CARD
    args = [
        "release-dataset",
        "--dataset_root",
        str(root),
        "--card",
        str(card),
        "--repo_id",
        "me/ds",
        "--push",
        "--output_dir",
        str(tmp_path / "release"),
    ]
    wrong = "hf_wrongTokenAlsoSecret987"
    with FakeHub(token=TOKEN) as hub:
        result = run_cli(args, hub_env(hub, tmp_path / "hf_home", token=wrong))
        assert hub.repos == {}
    assert result.returncode == 2
    assert "python -m openfly_agent.hub release-dataset: " in result.stderr and "401" in result.stderr
    assert wrong not in result.stdout + result.stderr


def test_push_refuses_offline_mode(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(PushError, match="unset HF_HUB_OFFLINE"):
        push_folder(tmp_path, "me/x")


def test_push_without_token_says_how_to_log_in(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr("huggingface_hub.get_token", lambda: None)
    with pytest.raises(PushError, match="HF_TOKEN or run `hf auth login`"):
        push_folder(tmp_path, "me/x")


def test_push_needs_the_folder(tmp_path):
    with pytest.raises(PushError, match="does not exist"):
        push_folder(tmp_path / "missing", "me/x")


@pytest.mark.parametrize("command", ["release-dataset", "release"])
@pytest.mark.parametrize("hub_state", ["unreachable", "offline"])
def test_push_without_a_hub_fails_before_writing_anything(command, hub_state, tmp_path):
    """`--push` with the Hub unreachable (or offline mode on) stops at once, in one line, with no folder."""
    from bridge_fakes import free_port

    out = tmp_path / "release"
    args = [command, "--repo_id", "me/x", "--push", "--output_dir", str(out)]
    if command == "release-dataset":
        root, _ = make_dataset_root(tmp_path / "data")
        args += ["--dataset_root", str(root), "--card", str(CARD)]
    else:  # checked after the Hub: the folder does not even need to exist
        args += ["--checkpoint", str(tmp_path / "checkpoint")]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGINGFACE_"))}
    env.update(HF_TOKEN=TOKEN, HF_HOME=str(tmp_path / "hf_home"), PYTHONPATH=str(REPO_ROOT))
    env.update(HF_ENDPOINT=f"http://127.0.0.1:{free_port()}", HF_HUB_DISABLE_TELEMETRY="1")
    env["HF_HUB_OFFLINE"] = "1" if hub_state == "offline" else "0"
    result = run_cli(args, env)
    assert result.returncode == 2
    errors = result.stderr.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith(f"python -m openfly_agent.hub {command}: "), (
        result.stderr[-2000:]
    )
    expected = "unset HF_HUB_OFFLINE" if hub_state == "offline" else f"{env['HF_ENDPOINT']} cannot be reached"
    assert expected in errors[0] and TOKEN not in result.stderr
    assert not out.exists()  # nothing written: the same command works once the Hub is back

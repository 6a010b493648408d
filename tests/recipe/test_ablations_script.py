"""scripts/ablations.sh: which recipe commands it runs for which arm (a recording stand-in for the venv's python)."""

from __future__ import annotations

import os
import shlex
import subprocess

from openfly_agent.utils.config import REPO_ROOT

SCRIPT = REPO_ROOT / "scripts" / "ablations.sh"


def _fake_venv(tmp_path):
    """A VENV whose bin/python appends its arguments to calls.txt (one line per call) and exits 0."""
    log = tmp_path / "calls.txt"
    python = tmp_path / "venv" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text(f'#!/usr/bin/env bash\necho "$*" >> {shlex.quote(str(log))}\n')
    python.chmod(0o755)
    return tmp_path / "venv", log


def _run(tmp_path, arms: str) -> subprocess.CompletedProcess:
    venv, _ = _fake_venv(tmp_path)
    env = {**os.environ, "VENV": str(venv), "ROOT": str(tmp_path / "abl"), "ARMS": arms}
    return subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True)


def test_each_arm_runs_its_config_and_shares_the_recipes_grounding_stage_where_only_navigation_changes(
    tmp_path,
):
    root = tmp_path / "abl"
    (root / "recipe" / "navigation").mkdir(parents=True)
    (root / "recipe" / "navigation" / ".recipe_done").write_text("{}\n")
    done = _run(tmp_path, "current_frame no_grounding_pretraining with_dagger")
    assert done.returncode == 0, done.stderr
    calls = (tmp_path / "calls.txt").read_text().splitlines()
    assert (
        calls[0]
        == f"-m openfly_agent.recipe --config_path configs/recipe/tiny-recipe.yaml --output_dir {root}/recipe"
    )
    shared, random = f"--grounding_from {root}/recipe/grounding", "--eval.baselines=[random]"
    assert calls[1].endswith(
        f"ablations/current_frame.yaml --output_dir {root}/current_frame {random} {shared}"
    )
    assert calls[2].endswith(
        f"ablations/no_grounding_pretraining.yaml --output_dir {root}/no_grounding_pretraining {random}"
    )
    assert calls[3].endswith(f"ablations/with_dagger.yaml --output_dir {root}/with_dagger {random} {shared}")
    assert (root / "with_dagger" / "navigation" / ".recipe_done").is_file()  # DAgger starts from the recipe's
    table = f"bench/ablation_table.py --run keyframes_merging={root}/recipe --run current_frame={root}/current_frame"
    assert calls[4].startswith(table) and calls[4].endswith(f"--json {root}/table.json")


def test_an_unknown_arm_stops_the_script_before_anything_runs(tmp_path):
    done = _run(tmp_path, "current_frame no_such_arm")
    assert done.returncode == 2 and "no arm no_such_arm" in done.stderr
    assert not (tmp_path / "calls.txt").exists()


def test_the_long_route_arms_share_the_full_agents_grounding_stage(tmp_path):
    root = tmp_path / "abl"
    venv, log = _fake_venv(tmp_path)
    guards = "--grounding.minutes=300 --navigation.minutes=300"
    env = {
        **os.environ,
        "VENV": str(venv),
        "ROOT": str(root),
        "ARMS": "current_frame random_keyframes",
        "RECIPE_ARGS": guards,
    }
    done = subprocess.run(
        ["bash", str(REPO_ROOT / "scripts" / "long_ablations.sh")], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    calls = log.read_text().splitlines()
    first = f"{root}/keyframes_merging"
    assert calls[0].endswith(f"long-ablations/keyframes_merging.yaml --output_dir {first} {guards}")
    shared = f"--eval.baselines=[random] --grounding_from {first}/grounding {guards}"
    assert calls[1].endswith(f"long-ablations/current_frame.yaml --output_dir {root}/current_frame {shared}")
    assert calls[2].endswith(
        f"long-ablations/random_keyframes.yaml --output_dir {root}/random_keyframes {shared}"
    )
    table = f"--run keyframes_merging={first} --run current_frame={root}/current_frame"
    assert table in calls[3] and calls[3].endswith(f"--json {root}/table.json")
    # the same rows against current frame only, which leads
    others = f"--run keyframes_merging={first} --run random_keyframes={root}/random_keyframes"
    assert f"--run current_frame={root}/current_frame {others} --json" in calls[4]
    assert calls[4].endswith(f"--json {root}/table-vs-current-frame.json") and len(calls) == 5

"""`eval.py --checkpoint`: a checkpoint that cannot act is refused in one line (resolution: tests/rollout)."""

from __future__ import annotations

import json
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.rollout.checkpoints import checkpoint_folder


def test_eval_refuses_a_grounding_stage_checkpoint_naming_the_navigation_stage(tmp_path, capsys):
    """`eval.py --checkpoint <job>/grounding`: exit 2, one line naming <job>/navigation, nothing written."""
    from data_factories import make_episode, make_frames

    from openfly_agent.data.writer import OpenFlyDatasetWriter

    dataset = tmp_path / "data"
    writer = OpenFlyDatasetWriter(dataset)
    episode = make_episode("env_ue_smallcity/astar_data/low_short/ep0", [1, 2, 0], split=C.SPLIT_TEST_SEEN)
    writer.write_episode(episode, make_frames(len(episode)))
    writer.finalize()
    for stage in ("grounding", "navigation"):
        step = tmp_path / "job" / stage / "checkpoints" / "step-000004"
        step.mkdir(parents=True)
        (step / "config.json").write_text('{"model_type": "openfly_agent"}')
        (step / "train_config.json").write_text(json.dumps({"stage": stage, "steps": 4}))
        (step.parent / "last").symlink_to("step-000004")
    from eval_helpers import eval_main

    out = tmp_path / "out"
    argv = [
        "--checkpoint", str(tmp_path / "job" / "grounding"), f"--split=[{C.SPLIT_TEST_SEEN}]", "--plots=0",
        "--progress=false", f"--dataset_root={dataset}", f"--output_dir={out}",
    ]  # fmt: skip
    assert eval_main()(argv) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert "grounding-stage checkpoint" in line and str(tmp_path / "job" / "navigation") in line
    assert not out.exists()
    assert checkpoint_folder(str(tmp_path / "job" / "navigation")).name == "step-000004"  # the stage to use


def test_a_truncated_checkpoint_is_one_line_and_writes_nothing(tmp_path):
    """eval.py on a model.safetensors cut in half: one line naming the file, exit 2, no output folder."""
    import os
    import sys

    from eval_helpers import save_small_agent

    from openfly_agent.utils.processes import run_group

    folder = tmp_path / "ckpt"
    save_small_agent(folder, ["fly to the red tower"])
    weights = folder / "model.safetensors"
    with open(weights, "r+b") as f:
        f.truncate(weights.stat().st_size // 2)
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(repo), "HF_HUB_OFFLINE": "1", "TOKENIZERS_PARALLELISM": "false"}
    command = [sys.executable, str(repo / "eval.py"), "--checkpoint", str(folder)]
    command += ["--dataset_root", str(tmp_path / "data"), "--output_dir", str(tmp_path / "out")]
    done = run_group(command, timeout=300, env=env)
    assert done.returncode == 2, done.stderr[-3000:]
    assert done.stderr.strip().splitlines() == [
        f"eval.py: {weights} is not a readable safetensors file (Error while deserializing header: incomplete "
        "metadata, file not fully covered): it is truncated or corrupt; copy or download it again"
    ]
    assert not (tmp_path / "out").exists()

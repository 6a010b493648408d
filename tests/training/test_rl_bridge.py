"""The RL stage through an engine bridge: `train_rl(cfg, env)` flies the tiny navigation run of conftest.py in two
3DGS bridges (sim/bridges/gs_http.py) against the fake SIBR server of tests/bridge_fakes.py, from the train routes
of a dataset whose scenes are 3DGS scenes, and updates the policy on the frames the bridge rendered; nothing it
opened stays open."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
from bridge_fakes import FakeSIBR, make_frame_bgr
from conftest import checkpoint_weights, make_config, reset_accelerate
from test_rl_stage import rl_logs

from openfly_agent.sim.bridges.gs_http import GSHttpBridge, GSHttpConfig
from openfly_agent.sim.real_scene import GS_SCALE_RATIOS
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.training.rl_trainer import train_rl

# the generated dataset's embedded scenes, renamed to 3DGS scenes of the benchmark
GS_SCENES = {"embedded-0": "env_gs_nwpu01", "embedded-1": "env_gs_sjtu01", "embedded-2": "env_gs_nwpu02"}


@pytest.fixture(scope="module")
def gs_dataset(generated_dataset, tmp_path_factory) -> Path:
    """The generated dataset with its scenes renamed to 3DGS ones (folders, annotations, metadata): routes that
    the embedded city does not fly, the scenes a 3DGS bridge renders."""
    root = tmp_path_factory.mktemp("gs") / "tiny-gs"
    for path in sorted(generated_dataset.rglob("*")):
        relative = str(path.relative_to(generated_dataset))
        for embedded, gs in GS_SCENES.items():
            relative = relative.replace(embedded, gs)
        target = root / relative
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif path.suffix in (".json", ".jsonl"):
            text = path.read_text()
            for embedded, gs in GS_SCENES.items():
                text = text.replace(embedded, gs)
            target.write_text(text)
        else:
            shutil.copyfile(path, target)
    assert set(GS_SCENES.values()) <= set(GS_SCALE_RATIOS)
    return root


def open_sockets() -> set[str]:
    """This process's open sockets: the `socket:[inode]` targets of its file descriptors (Linux /proc)."""
    targets = set()
    for fd in Path("/proc/self/fd").iterdir():
        try:
            targets.add(os.readlink(fd))
        except OSError:  # the descriptor that listed the folder, closed since
            continue
    return {t for t in targets if t.startswith("socket:")}


def child_processes() -> set[int]:
    """The ids of this process's children (Linux /proc, every thread's)."""
    tasks = Path("/proc/self/task").iterdir()
    return {int(pid) for task in tasks for pid in (task / "children").read_text().split()}


def test_rl_updates_the_policy_on_a_bridges_frames(gs_dataset, reference_run, tmp_path):
    navigation_run, _ = reference_run
    out = tmp_path / "rl"
    cfg = make_config(
        gs_dataset, out, stage="rl", init__checkpoint=str(navigation_run), steps=1, rl__group_size=2,
        rl__episodes_per_update=1, rl__max_steps=3, rl__num_envs=2, rl__progress_weight=1.0, rl__minibatches=1,
        optim__lr=1e-3, checkpoint__save_interval=1,
    )  # fmt: skip
    sockets_before, children_before = open_sockets(), child_processes()
    with FakeSIBR(make_frame_bgr(64, 64)) as server:
        bridges = [GSHttpBridge(GSHttpConfig(port=server.port, read_timeout_s=30)) for _ in range(2)]
        reset_accelerate()
        try:
            with VectorSimulator(sims=bridges) as env:
                run = train_rl(cfg, env)
                frame_dirs = [bridge._output_dir for bridge in bridges]  # the bridges' own temporary folders
        finally:
            reset_accelerate()
        renders, gets = len(server.forms), server.gets
    figures = rl_logs(out)[1]
    # 2 rollouts flown on the bridge: each renders its start and every move (a STOP renders nothing)
    steps = int(figures["rollout_steps"])
    assert run.state.step == 1 and steps > 0 and figures["samples_trained"] > 0
    assert steps <= renders <= steps + 2 and gets >= 2  # each bridge said hello (GET /) before rendering
    assert "grounding_loss" not in figures  # the bridge reports no boxes: no grounding target was trained
    assert all(name in figures for name in ("reward", "kl", "entropy", "pg_loss", "success_rate"))
    start = checkpoint_weights(navigation_run / "checkpoints" / "last")
    trained = checkpoint_weights(out / "checkpoints" / "last")
    assert any(not torch.equal(start[k], trained[k]) for k in start), "the update left every weight unchanged"
    # closed: the bridges' folders removed, no socket or child process left behind, the server stopped
    assert all(folder is not None and not folder.exists() for folder in frame_dirs)
    assert open_sockets() <= sockets_before and child_processes() <= children_before
    assert not server._thread.is_alive()

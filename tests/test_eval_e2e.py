"""End to end on a generated split: baselines and a tiny agent through `eval.run`, resume, processes."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from eval_helpers import generate_tiny_dataset, save_small_agent
from hold_probe import HOLDING
from PIL import Image

from openfly_agent import constants as C
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.eval.baselines import make_baseline
from openfly_agent.eval.config import EvalConfig
from openfly_agent.eval.distributed import ProcessInfo, read_all_logs
from openfly_agent.eval.factory import make_env
from openfly_agent.eval.report import policy_results
from openfly_agent.eval.run import run
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.utils.processes import communicate_group, run_group, running

REPO = Path(__file__).resolve().parents[1]
SPLITS = [C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("embedded-tiny")
    generate_tiny_dataset(root)
    return root


def _cfg(dataset, out, **kw):
    base = {
        "dataset_root": str(dataset),
        "output_dir": str(out),
        "progress": False,
        "plots": 1,
        "batch_size": 4,
    }
    return EvalConfig(**{**base, **kw})


def test_oracle_and_stop_at_start_on_a_generated_split(dataset, tmp_path):
    outcome = run(_cfg(dataset, tmp_path, policy="oracle", baselines=["stop"]))
    # Every oracle episode replays its actions through the simulator (no teleport) and stops.
    assert {r.end_reason for r in read_all_logs(tmp_path / "oracle")} == {"stop"}
    for split in SPLITS:
        episodes = load_openfly_dataset(dataset, split)  # the default reader options, as eval's
        distances = [np.linalg.norm(e.goal - e.positions[0]) for e in episodes]
        # The planner stops within 3.1 m of its goal: the oracle's NE is that leftover.
        leftover = [np.linalg.norm(e.goal - e.positions[-1]) for e in episodes]
        assert max(leftover) < 3.2
        for profile in ("openfly", "standard"):
            oracle = outcome["results"]["oracle"]["splits"][split][profile]["overall"]
            assert oracle["sr_pct"] == 100.0 and oracle["ne_m"] == pytest.approx(np.mean(leftover))
            stop = outcome["results"]["stop"]["splits"][split][profile]["overall"]
            assert stop["episodes"] == len(episodes)
            assert stop["sr_pct"] == pytest.approx(100.0 * np.mean([d < 20.0 for d in distances]))
            assert stop["ne_m"] == pytest.approx(np.mean(distances))
            # STOP as action 0: every failure is an early STOP, not a miss after flying
            assert stop["early_stop_pct"] == pytest.approx(100.0 - stop["sr_pct"])
            assert stop["stopped_far_pct"] == 0.0
            assert oracle["step_limit_pct"] == stop["step_limit_pct"] == 0.0
    summary = (tmp_path / "summary.md").read_text()
    assert "| oracle | " in summary and "| stop | " in summary
    assert (
        f"### {C.SPLIT_TEST_UNSEEN} - where the episodes end" in summary
        and "| stop / `standard` |" in summary
    )
    assert list((tmp_path / "oracle" / "plots" / C.SPLIT_TEST_UNSEEN).glob("*.png"))
    # Every table equals the one recomputed from the JSONL alone.
    for name in ("oracle", "stop"):
        written = json.loads((tmp_path / name / C.RESULTS_JSON).read_text())
        assert (
            written["splits"]
            == policy_results(name, read_all_logs(tmp_path / name), written["profiles"])["splits"]
        )


def test_compare_pairs_two_policies_of_real_eval_outputs(dataset, tmp_path):
    from openfly_agent.eval.compare import PairingError, compare_folders

    outcome = run(_cfg(dataset, tmp_path / "full", policy="oracle", baselines=["stop"], plots=0))
    pair = compare_folders(tmp_path / "full" / "stop", tmp_path / "full" / "oracle", resamples=200)
    for split in SPLITS:
        stop = outcome["results"]["stop"]["splits"][split]["standard"]["overall"]
        row = pair["splits"][split]["standard"]
        # the oracle succeeds everywhere: each episode is "both" where STOP at the start succeeds, else "only B"
        both = round(stop["sr_pct"] * stop["episodes"] / 100)
        assert row["counts"] == {"both": both, "only_a": 0, "only_b": stop["episodes"] - both, "neither": 0}
        assert row["sr_diff_pp"] == pytest.approx(100.0 - stop["sr_pct"])
    run(_cfg(dataset, tmp_path / "subset", policy="stop", max_episodes=2, plots=0))
    with pytest.raises(PairingError, match="flew other episodes"):
        compare_folders(tmp_path / "full" / "stop", tmp_path / "subset" / "stop")


@pytest.mark.parametrize("name", ["forward", "random"])
def test_blind_baselines_equal_the_rendering_simulator(dataset, name):
    cfg = _cfg(dataset, "unused", policy=name, max_steps=40)
    episodes = load_openfly_dataset(dataset, C.SPLIT_TEST_UNSEEN)
    results = {}
    for render in (False, True):
        env = make_env(cfg, ProcessInfo(), episodes, render=render)
        records = []
        policy = make_baseline(name, episodes, seed=1)
        LockstepRunner(policy, env, cfg.max_steps, show_progress=False).run(episodes, "s", records.append)
        env.close()
        results[render] = sorted(records, key=lambda r: r.episode_id)
    assert results[False] == results[True]
    if name == "forward":
        assert any(r.collision_steps for r in results[True])  # the straight flights hit buildings


def test_agent_batched_equals_batch_one_and_logs_boxes(dataset, tmp_path):
    episodes = load_openfly_dataset(dataset, C.SPLIT_TRAIN)
    save_small_agent(tmp_path / "ckpt", [e.instruction for e in episodes])
    common = {
        "policy": "agent",
        "checkpoint": str(tmp_path / "ckpt"),
        "max_steps": 5,
        "plots": 0,
        "max_episodes": 2,
    }
    gif = load_openfly_dataset(dataset, C.SPLIT_TEST_SEEN)[0].episode_id  # (sorted ids: within max_episodes)
    outcomes = [
        run(_cfg(dataset, tmp_path / f"b{b}", batch_size=b, gif_episodes=[gif] if b == 1 else [], **common))
        for b in (1, 4)
    ]
    one, many = (read_all_logs(tmp_path / f"b{b}" / "agent") for b in (1, 4))
    assert len(one) == len(many) == 4
    for a, b in zip(one, many):
        assert (a.actions, a.poses, a.keyframes, a.collision_steps) == (
            b.actions,
            b.poses,
            b.keyframes,
            b.collision_steps,
        )
        assert [x is None for x in a.boxes] == [x is None for x in b.boxes]
        np.testing.assert_allclose([x for x in a.boxes if x], [x for x in b.boxes if x], atol=1e-4)
    assert outcomes[0]["results"]["agent"]["splits"] == outcomes[1]["results"]["agent"]["splits"]
    boxes = [b for r in one for b in r.boxes]
    assert len(boxes) == sum(len(r.actions) for r in one)
    assert all(b is None or (len(b) == 4 and all(0.0 <= v <= 1.0 for v in b)) for b in boxes)
    assert all(isinstance(k, list) and len(r.keyframes) == len(r.actions) for r in one for k in r.keyframes)
    (gif_file,) = (tmp_path / "b1" / "agent" / "gifs").glob("*.gif")
    record = next(r for r in one if r.episode_id == gif)
    assert Image.open(gif_file).n_frames == len(record.actions)  # one frame per decision


def test_agent_true_box_flies_on_the_simulators_target_boxes(dataset, tmp_path, monkeypatch):
    """`agent_true_box`: the same checkpoint, its box token and memory fed the true target box at every step."""
    from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_STEP, OBS_TARGET_BOX

    episodes = load_openfly_dataset(dataset, C.SPLIT_TRAIN)
    save_small_agent(tmp_path / "ckpt", [e.instruction for e in episodes])
    true_boxes, real = {}, LockstepRunner._observation

    def spy(runner, running):
        obs = real(runner, running)
        if OBS_TARGET_BOX in obs:
            true_boxes[(obs[OBS_EPISODE_ID], obs[OBS_STEP])] = obs[OBS_TARGET_BOX]
        return obs

    monkeypatch.setattr(LockstepRunner, "_observation", spy)
    cfg = _cfg(
        dataset, tmp_path / "out", policy="agent", baselines=["agent_true_box"], checkpoint=str(tmp_path / "ckpt"),
        max_steps=6, plots=0, max_episodes=2, batch_size=2,
    )  # fmt: skip
    outcome = run(cfg)
    records = read_all_logs(tmp_path / "out" / "agent_true_box")
    assert len(records) == 4 and set(outcome["results"]) == {"agent", "agent_true_box"}
    steps = [(r, t) for r in records for t in range(len(r.actions))]
    assert len(true_boxes) == len(steps)  # only this policy was handed the true boxes
    assert any(true_boxes.values()) and any(box is None for box in true_boxes.values())
    for record, t in steps:  # the box it flew on is the simulator's, not its head's
        expected = true_boxes[(record.episode_id, t)]
        assert (record.boxes[t] is None) == (expected is None)
        if expected is not None:
            assert record.boxes[t] == pytest.approx(expected, abs=1e-6)
    agent = read_all_logs(tmp_path / "out" / "agent")
    assert [r.boxes for r in agent] != [r.boxes for r in records]


def test_agent_true_box_of_the_current_leg_on_chained_routes(tmp_path, monkeypatch):
    """`--true_box=leg`: on routes past 2 landmarks, `agent_true_box` is handed the box of the target of the leg
    the drone is on (the first target until it comes within the success radius of the first leg's goal)."""
    from openfly_agent.rollout.legs import current_leg
    from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_STEP, OBS_TARGET_BOX

    dataset = tmp_path / "chained"
    generate_tiny_dataset(dataset, chained=True)
    episodes = {e.episode_id: e for e in load_openfly_dataset(dataset, C.SPLIT_TEST_UNSEEN)}
    assert all(len(e.leg_goals) == len(e.landmark_ids) == 2 for e in episodes.values())
    save_small_agent(tmp_path / "ckpt", [e.instruction for e in episodes.values()])
    handed, real = {}, LockstepRunner._observation

    def spy(runner, running):  # the box handed over, and every landmark's box in the same frame
        obs = real(runner, running)
        handed[(obs[OBS_EPISODE_ID], obs[OBS_STEP])] = (obs[OBS_TARGET_BOX], dict(running.obs.boxes or {}))
        return obs

    monkeypatch.setattr(LockstepRunner, "_observation", spy)
    cfg = _cfg(
        dataset, tmp_path / "out", policy="agent_true_box", checkpoint=str(tmp_path / "ckpt"), true_box="leg",
        split=[C.SPLIT_TEST_UNSEEN], max_steps=8, plots=0, max_episodes=3, batch_size=3,
    )  # fmt: skip
    run(cfg)
    records = read_all_logs(tmp_path / "out" / "agent_true_box")
    assert len(records) == 3 and len(handed) == sum(len(r.actions) for r in records)
    not_final = 0
    for record in records:
        episode, leg = episodes[record.episode_id], 0
        for t, pose in enumerate(record.poses[: len(record.actions)]):
            leg = current_leg(leg, np.asarray(pose[:3]), episode.leg_goals, C.SUCCESS_RADIUS_M)
            got, frame_boxes = handed[(record.episode_id, t)]
            expected = frame_boxes.get(episode.landmark_ids[leg])
            assert (got is None) == (expected is None), (record.episode_id, t)
            if expected is not None:
                assert got == pytest.approx(list(expected), abs=1e-6)
            final = frame_boxes.get(episode.landmark_ids[-1])
            not_final += (got is None) != (final is None) or (
                got is not None and got != pytest.approx(list(final))
            )
    assert not_final > 0  # steps at which the final target's box (`true_box=final`) would have differed
    assert (
        json.loads((tmp_path / "out" / "agent_true_box" / "run_identity.json").read_text())["true_box"]
        == "leg"
    )


def test_agent_resumed_after_a_kill_equals_an_uninterrupted_run_bit_for_bit(dataset, tmp_path):
    """A kill after some episodes, then the same command: every record, predicted boxes included, is exactly
    the uninterrupted run's (lockstep groups are recomputed whole, with the same companions)."""
    episodes = load_openfly_dataset(dataset, C.SPLIT_TRAIN)
    save_small_agent(tmp_path / "ckpt", [e.instruction for e in episodes])
    common = {"policy": "agent", "checkpoint": str(tmp_path / "ckpt"), "max_steps": 12, "plots": 0}
    common.update(batch_size=3, split=[C.SPLIT_TEST_UNSEEN])
    run(_cfg(dataset, tmp_path / "clean", **common))
    clean = read_all_logs(tmp_path / "clean" / "agent")
    assert len(clean) > 3 and any(b is not None for r in clean for b in r.boxes)
    finished = (tmp_path / "clean" / "agent" / C.EPISODES_JSONL).read_text().splitlines(keepends=True)
    killed = tmp_path / "killed" / "agent"
    killed.mkdir(parents=True)
    # What SIGKILL leaves after 2 episodes finished: their lines, in finishing order, and half of the third.
    (killed / C.EPISODES_JSONL).write_text("".join(finished[:2]) + finished[2][:40])
    run(_cfg(dataset, tmp_path / "killed", **common))
    assert read_all_logs(killed) == clean  # boxes compared exactly, not to a tolerance


def _held_eval_cmd(hold: str, dataset, out) -> list[str]:
    """`_eval_cmd` under tests/hold_probe.py, held at `hold` until a signal."""
    command = _eval_cmd(dataset, out)
    return [command[0], str(REPO / "tests" / "hold_probe.py"), hold, *command[1:]]


def _eval_cmd(dataset, out, *extra):
    return [
        sys.executable, str(REPO / "eval.py"), "--policy", "random", "--baselines=[forward]",
        "--dataset_root", str(dataset), "--output_dir", str(out), "--batch_size=2", "--plots=0",
        "--progress=false", *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def reference(dataset, tmp_path_factory):
    """An uninterrupted single-process run of `_eval_cmd`'s settings, in this process."""
    out = tmp_path_factory.mktemp("reference")
    run(_cfg(dataset, out, policy="random", baselines=["forward"], batch_size=2, plots=0))
    return out


def _same_results(a: Path, b: Path) -> None:
    for name in ("random", "forward"):
        assert read_all_logs(a / name) == read_all_logs(b / name)
        assert (
            json.loads((a / name / C.RESULTS_JSON).read_text())["splits"]
            == json.loads((b / name / C.RESULTS_JSON).read_text())["splits"]
        )


def _held(proc: subprocess.Popen) -> str:
    """`proc`'s stderr up to tests/hold_probe.py's line saying it holds (asserts that it does)."""
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if HOLDING in line:
            return "".join(seen)
    raise AssertionError(f"eval.py ended before the hold: {''.join(seen)[-3000:]}")


def test_sigkilled_run_resumes_to_the_same_table(dataset, reference, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    total = len((reference / "random" / C.EPISODES_JSONL).read_text().splitlines())
    assert total > 2
    log = tmp_path / "random" / C.EPISODES_JSONL
    # held once 2 episodes are written (tests/hold_probe.py): the kill lands half way however slow the machine
    with running(
        _held_eval_cmd("episodes:2", dataset, tmp_path), env=env, stderr=subprocess.PIPE, text=True
    ) as proc:
        _held(proc)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert len(log.read_bytes().splitlines()) == 2
    resumed = run_group(_eval_cmd(dataset, tmp_path), timeout=300, env=env)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "| random |" in resumed.stdout
    _same_results(reference, tmp_path)


def test_ctrl_c_ends_with_one_line_and_130_then_the_same_command_resumes(dataset, reference, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    # SIGINT back to its default in the child: a shell starts background jobs (`pytest ... &`) with it ignored
    default_sigint = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    # held once an episode is written (tests/hold_probe.py): Ctrl-C lands mid-run however slow the machine
    command = _held_eval_cmd("episodes:1", dataset, tmp_path)
    with running(command, env=env, preexec_fn=default_sigint, **pipes) as proc:
        before = _held(proc)
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends to the foreground process
        _, rest = communicate_group(proc, timeout=60)
    err = before + rest
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1] == "eval.py: interrupted; run the same command again to resume"
    resumed = run_group(_eval_cmd(dataset, tmp_path), timeout=300, env=env)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    _same_results(reference, tmp_path)


def test_two_processes_split_and_merge(dataset, reference, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    double = run_group(launcher + _eval_cmd(dataset, tmp_path)[1:], timeout=300, env=env)
    assert double.returncode == 0, double.stdout[-3000:] + double.stderr[-6000:]
    assert sorted(p.name for p in (tmp_path / "random").glob("episodes*.jsonl")) == [C.EPISODES_JSONL]
    # Each process ran its own shard (not the whole split), and only rank 0 printed the table.
    total = len(load_openfly_dataset(dataset, C.SPLIT_TEST_SEEN))
    # rank 0 alone logs INFO (each line once), naming both shards
    [(count, first, second)] = re.findall(
        r"random / test_seen: (\d+) episodes in 2 shards of (\d+), (\d+)", double.stderr
    )
    assert int(count) == total and sorted([int(first), int(second)]) == [total // 2, total - total // 2]
    assert double.stdout.count("| random |") == 4  # 2 splits x 2 profiles, once
    _same_results(reference, tmp_path)


def test_released_checkpoint_runs_through_the_compat_path(dataset, tmp_path):
    from eval_helpers import NORM_STATS, save_released_format_agent

    from openfly_agent.rollout.agent import AgentPolicy
    from openfly_agent.rollout.checkpoints import checkpoint_kind, load_agent

    episodes = load_openfly_dataset(dataset, C.SPLIT_TEST_UNSEEN)[:3]
    source = save_released_format_agent(tmp_path / "released", [e.instruction for e in episodes])
    assert checkpoint_kind(tmp_path / "released") == "openvla"
    model_config = str(tmp_path / "released" / "model.yaml")
    loaded = load_agent(str(tmp_path / "released"), "cpu", unnorm_key="vln_norm", model_config=model_config)
    assert loaded.action_tokenizer.decode_rule == "nearest"
    q99 = loaded.action_tokenizer.action_stats["q99"]
    np.testing.assert_array_equal(q99, NORM_STATS["vln_norm"]["action"]["q99"])
    source.set_action_decoding(
        decode_rule="nearest", unnorm_key="vln_norm"
    )  # through its config, as load_agent
    cfg = _cfg(dataset, tmp_path, policy="stop", max_steps=5)
    runs = []
    for agent in (loaded, source):  # the folder's agent flies exactly like the one that wrote it
        env = make_env(cfg, ProcessInfo(), episodes, render=True)
        records = []
        LockstepRunner(AgentPolicy(agent.new_session()), env, cfg.max_steps, show_progress=False).run(
            episodes, "s", records.append
        )
        env.close()
        runs.append(records)
    # Same actions and poses; the boxes differ: the grounding head is not in a released checkpoint and is
    # initialised afresh on load.
    for a, b in zip(*runs):
        assert (a.actions, a.poses, a.collision_steps) == (b.actions, b.poses, b.collision_steps)
    assert all(0 <= a <= 9 for r in runs[0] for a in r.actions)

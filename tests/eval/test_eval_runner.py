"""The lockstep runner with baselines on a pose-only simulator: batching, oracle, stop-at-start, resume."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import numpy as np
import pytest
from eval_helpers import PoseSimulator, make_episode, wall_grid

from openfly_agent import constants as C
from openfly_agent.eval.baselines import ConstantPolicy, OraclePolicy, RandomPolicy, make_baseline
from openfly_agent.eval.config import EvalConfig
from openfly_agent.eval.distributed import ProcessInfo, read_all_logs
from openfly_agent.eval.outputs import write_policy_outputs
from openfly_agent.eval.records import EpisodeLog
from openfly_agent.eval.report import policy_results
from openfly_agent.eval.rollout import teleport_record
from openfly_agent.eval.run import evaluate_policy, prepare_output
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.sim.base import StepInfo
from openfly_agent.sim.vector import VectorSimulator

SPLIT = C.SPLIT_TEST_SEEN


def _episodes():
    """Six replayable episodes of different lengths in two scenes, one of them heading into the wall."""
    routes = [
        [9, 0],  # goal 9 m ahead: stop-at-start succeeds
        [9, 9, 9, 9, 0],  # 36 m
        [2, 1, 1, 9, 0],  # turn then fly
        [4, 4, 1, 8, 3, 9, 0],
        [9] * 12 + [0],  # 108 m: a long one
        [1, 0],
    ]
    return [
        make_episode(f"scene-{i % 2}/astar_data/low_short/t{i:02d}", r, scene_id=f"scene-{i % 2}")
        for i, r in enumerate(routes)
    ]


def _run(policy, episodes, batch, max_steps=C.MAX_EPISODE_STEPS, grid=None):
    records = []
    env = VectorSimulator(sims=[PoseSimulator(grid) for _ in range(batch)])
    LockstepRunner(policy, env, max_steps, show_progress=False).run(episodes, SPLIT, records.append)
    return sorted(records, key=lambda r: r.episode_id)


@pytest.mark.parametrize("name", ["random", "forward", "oracle"])
def test_batched_equals_batch_one(name):
    episodes = _episodes()
    one = _run(make_baseline(name, episodes, seed=3), episodes, batch=1, max_steps=40, grid=wall_grid(60.0))
    many = _run(make_baseline(name, episodes, seed=3), episodes, batch=4, max_steps=40, grid=wall_grid(60.0))
    assert one == many
    assert len(one) == len(episodes)


def test_random_policy_is_seeded_per_episode():
    a, b = RandomPolicy(seed=1), RandomPolicy(seed=1)
    a.reset(["x", "y"])
    b.reset(["y"])
    seq_a = [a.act([{"episode_id": "y", "step": t}])[0] for t in range(30)]
    seq_b = [b.act([{"episode_id": "y", "step": t}, {"episode_id": "x", "step": t}])[0] for t in range(30)]
    assert seq_a == seq_b
    assert set(seq_a) <= set(C.MODEL_ACTION_IDS) and len(set(seq_a)) > 3
    c = RandomPolicy(seed=2)
    c.reset(["y"])
    assert [c.act([{"episode_id": "y", "step": t}])[0] for t in range(30)] != seq_a


def test_oracle_reaches_every_goal_under_both_profiles():
    episodes = _episodes()
    records = _run(OraclePolicy(episodes), episodes, batch=3)
    for record, episode in zip(records, sorted(episodes, key=lambda e: e.episode_id)):
        assert record.actions == [int(a) for a in episode.actions]
        assert record.stopped and record.end_reason == "stop"
        np.testing.assert_allclose(record.poses[-1][:3], episode.goal, atol=1e-9)
    results = policy_results("oracle", records, ["openfly", "standard"])
    for profile in ("openfly", "standard"):
        overall = results["splits"][SPLIT][profile]["overall"]
        assert overall["sr_pct"] == 100.0 and overall["ne_m"] == pytest.approx(0.0, abs=1e-9)
        assert overall["episodes"] == 6
    assert results["splits"][SPLIT]["standard"]["overall"]["spl_pct"] == pytest.approx(100.0)


def test_stop_at_start_scores_what_the_definitions_give():
    episodes = _episodes()
    records = _run(ConstantPolicy("stop", C.ACTION_STOP), episodes, batch=2)
    assert all(r.actions == [0] and r.poses[0] == r.poses[1] for r in records)
    # Start-goal distances by hand, records sorted by id (scene-0: t00, t02, t04; scene-1: t01, t03, t05):
    # t00 9; t02 turn 30 deg then 15 straight; t04 108; t01 36; t03 up 6, forward 9, turn right 30 deg,
    # forward 9 -> |(9 + 9 cos 30, -9 sin 30, 6)|; t05 3.
    t03 = np.sqrt((9 + 9 * np.cos(np.pi / 6)) ** 2 + (9 * np.sin(np.pi / 6)) ** 2 + 36.0)
    distances = [9.0, 15.0, 108.0, 36.0, t03, 3.0]
    goals = [np.linalg.norm(np.asarray(r.goal) - np.asarray(r.poses[0][:3])) for r in records]
    np.testing.assert_allclose(goals, distances)
    within = [d for d in distances if d < 20.0]  # 4 of 6
    results = policy_results("stop", records, ["openfly", "standard"])
    of = results["splits"][SPLIT]["openfly"]["overall"]
    st = results["splits"][SPLIT]["standard"]["overall"]
    assert of["sr_pct"] == pytest.approx(400 / 6) and st["sr_pct"] == pytest.approx(400 / 6)
    # The official loop updates OSR after the STOP iteration too (pose = start), so OSR = SR (OpenFly#93).
    assert of["osr_pct"] == pytest.approx(400 / 6) and st["osr_pct"] == pytest.approx(400 / 6)
    assert of["ne_m"] == pytest.approx(sum(distances) / 6)
    # Official SPL = straight line / (0 + 0.001) for the successes; standard SPL = 1 for them.
    assert of["spl_pct"] == pytest.approx(100.0 * sum(d / 0.001 for d in within) / 6)
    assert st["spl_pct"] == pytest.approx(400 / 6)


def test_forward_hits_the_step_cap_and_the_wall():
    episodes = _episodes()
    records = _run(
        ConstantPolicy("forward", C.ACTION_FORWARD), episodes, batch=6, max_steps=25, grid=wall_grid(30.0)
    )
    straight = next(r for r in records if r.episode_id.endswith("t01"))  # yaw 0: toward the wall at x = 30
    assert len(straight.actions) == 25 and not straight.stopped and straight.end_reason == "max_steps"
    assert straight.collision_steps[0] == 9  # move k goes x = 3k -> 3k + 3: move 9 ends on the wall at x = 30
    assert straight.collision_steps == list(range(9, 25))
    m = policy_results("forward", [straight], ["openfly", "standard"])["splits"][SPLIT]
    assert m["standard"]["overall"]["collision_rate_pct"] == 100.0
    assert m["standard"]["overall"]["ne_m"] == pytest.approx(36.0 - 27.0)  # ends before the colliding move
    assert m["openfly"]["overall"]["ne_m"] == pytest.approx(75.0 - 36.0)  # collisions ignored: goes on


def test_engine_error_ends_only_that_episode():
    class FlakySimulator(PoseSimulator):
        def step(self, action_id: int):
            if self.pose.x > 10:
                raise ConnectionError("engine went away")
            return super().step(action_id)

    episodes = _episodes()
    env = VectorSimulator(sims=[FlakySimulator(), PoseSimulator()])
    records = []
    LockstepRunner(OraclePolicy(episodes), env, show_progress=False).run(episodes, SPLIT, records.append)
    failed = [r for r in records if r.end_reason == "error"]
    assert failed and all("engine went away" in r.error for r in failed)
    assert len(records) == len(episodes)


def test_teleport_oracle_follows_ground_truth_poses():
    episode = make_episode("s/astar_data/high_long/t", [9, 9, 0])
    episode.positions[2, 0] += 1.5  # a label / pose disagreement as in the released data
    episode.goal = episode.positions[-1].copy()
    oracle = OraclePolicy([episode])
    assert not oracle.replays(episode.episode_id)
    record = teleport_record(episode, SPLIT, "oracle", C.MAX_EPISODE_STEPS)
    assert record.stopped and record.end_reason == "teleport"
    np.testing.assert_allclose(np.asarray(record.poses)[:3, :3], episode.positions)
    results = policy_results("oracle", [record], ["openfly", "standard"])["splits"][SPLIT]
    assert (
        results["openfly"]["overall"]["sr_pct"] == 100.0 and results["standard"]["overall"]["sr_pct"] == 100.0
    )
    assert teleport_record(episode, SPLIT, "oracle", 1).end_reason == "max_steps"


class _Killed(Exception):
    pass


def test_killed_run_resumes_to_the_same_tables(tmp_path, monkeypatch):
    episodes = {SPLIT: _episodes(), C.SPLIT_TEST_UNSEEN: _episodes()[:3]}
    cfg = EvalConfig(policy="random", batch_size=2, plots=0, progress=False, seed=5, max_steps=30)
    info = ProcessInfo()

    def evaluate(folder, env_batch=2):
        prepare_output(folder, cfg.result_identity("random"), False, info)
        env = VectorSimulator(sims=[PoseSimulator(wall_grid(50.0)) for _ in range(env_batch)])
        evaluate_policy(cfg, RandomPolicy(cfg.seed), episodes, env, folder, info)

    evaluate(tmp_path / "full")
    full = write_policy_outputs(cfg, "random", read_all_logs(tmp_path / "full"), tmp_path / "full", episodes)

    # Kill after 4 finished episodes, leaving half a line behind, then resume with another batch size.
    killed = tmp_path / "killed"
    original_append = EpisodeLog.append
    calls = {"n": 0}

    def dying_append(self, record):
        calls["n"] += 1
        if calls["n"] > 4:
            with open(self.path, "a") as handle:
                handle.write(record.to_json()[:40])
            raise _Killed
        original_append(self, record)

    with monkeypatch.context() as patch:
        patch.setattr(EpisodeLog, "append", dying_append)
        with pytest.raises(_Killed):
            evaluate(killed)
    assert len(read_all_logs(killed)) == 4
    evaluate(killed, env_batch=3)
    resumed = write_policy_outputs(cfg, "random", read_all_logs(killed), killed, episodes)
    assert resumed["splits"] == full["splits"]
    assert len((killed / "episodes.jsonl").read_text().splitlines()) == 9

    # The printed table equals the table recomputed from the JSONL alone.
    written = json.loads((killed / "results.json").read_text())
    assert written["splits"] == policy_results("random", read_all_logs(killed), cfg.profiles)["splits"]


def _stop_distances():
    """Start-goal distances of `_episodes()` sorted by id (test_stop_at_start_scores_what_the_definitions_give)."""
    t03 = np.sqrt((9 + 9 * np.cos(np.pi / 6)) ** 2 + (9 * np.sin(np.pi / 6)) ** 2 + 36.0)
    return [9.0, 15.0, 108.0, 36.0, t03, 3.0]


def _evaluate_stop(folder, episodes):
    cfg = EvalConfig(policy="stop", batch_size=2, plots=0, progress=False)
    prepare_output(folder, cfg.result_identity("stop"), False, ProcessInfo())
    env = VectorSimulator(sims=[PoseSimulator() for _ in range(2)])
    evaluate_policy(cfg, ConstantPolicy("stop", C.ACTION_STOP), episodes, env, folder, ProcessInfo())
    return cfg


def test_episode_log_carries_each_profiles_scores(tmp_path):
    _evaluate_stop(tmp_path, {SPLIT: _episodes()})
    rows = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    rows.sort(key=lambda row: row["episode_id"])
    for row, distance in zip(rows, _stop_distances(), strict=True):
        assert set(row["metrics"]) == {"openfly", "standard"}
        for profile, scores in row["metrics"].items():
            success = distance < 20.0
            assert scores["ne"] == pytest.approx(distance), (row["episode_id"], profile)
            assert scores["success"] == scores["oracle_success"] == success
            # STOP as action 0: a failure there is an early STOP, not a miss after flying.
            assert scores["outcome"] == ("success" if success else "early_stop")
        assert row["metrics"]["standard"]["spl"] == (1.0 if distance < 20.0 else 0.0)


def test_old_log_rows_without_scores_give_the_same_tables(tmp_path):
    episodes = {SPLIT: _episodes()}
    cfg = _evaluate_stop(tmp_path / "new", episodes)
    new = write_policy_outputs(cfg, "stop", read_all_logs(tmp_path / "new"), tmp_path / "new", episodes)
    # The same log as version 1 wrote it (no `metrics`) for half the episodes, then resumed: nothing to run.
    lines = (tmp_path / "new" / "episodes.jsonl").read_text().splitlines()
    old = []
    for index, line in enumerate(lines):
        row = json.loads(line)
        if index % 2:
            del row["metrics"]
            row["version"] = 1
        old.append(json.dumps(row))
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "episodes.jsonl").write_text("\n".join(old) + "\n")
    _evaluate_stop(tmp_path / "old", episodes)
    assert len((tmp_path / "old" / "episodes.jsonl").read_text().splitlines()) == len(lines)
    records = read_all_logs(tmp_path / "old")
    assert sum(not r.metrics for r in records) == len(lines) // 2
    resumed = write_policy_outputs(cfg, "stop", records, tmp_path / "old", episodes)
    assert resumed["splits"] == new["splits"]


def test_resume_refuses_other_settings(tmp_path):
    cfg = EvalConfig(policy="random", progress=False)
    prepare_output(tmp_path / "random", cfg.result_identity("random"), False, ProcessInfo())
    other = EvalConfig(policy="random", seed=9, progress=False)
    with pytest.raises(ValueError, match="seed: 0 -> 9.*--overwrite"):
        prepare_output(tmp_path / "random", other.result_identity("random"), False, ProcessInfo())
    prepare_output(tmp_path / "random", other.result_identity("random"), True, ProcessInfo())


def test_resume_after_the_weights_were_saved_again_names_the_file_and_both_times(tmp_path):
    """eval.py's refusal names the rewritten weight file and both modification times in words (the run identity
    stores nanoseconds)."""
    identity = EvalConfig(policy="random", progress=False).result_identity("random")
    then = int(datetime(2026, 11, 27, 9, 14, 56, tzinfo=timezone.utc).timestamp()) * 10**9
    now = int(datetime(2026, 11, 27, 10, 2, 11, tzinfo=timezone.utc).timestamp()) * 10**9

    def weights(mtime_ns: int) -> dict:
        return {
            "folder": "/runs/a/checkpoints/step-000004",
            "weights": {"model.safetensors": [1234, mtime_ns]},
        }

    prepare_output(tmp_path / "agent", {**identity, "weights": weights(then)}, False, ProcessInfo())
    with pytest.raises(ValueError) as err:
        prepare_output(tmp_path / "agent", {**identity, "weights": weights(now)}, False, ProcessInfo())
    message = str(err.value)
    assert (
        "(weights: /runs/a/checkpoints/step-000004: model.safetensors was written again: 1,234 B modified "
        "2026-11-27 09:14:56 UTC then, 1,234 B modified 2026-11-27 10:02:11 UTC now); pass another --output_dir"
    ) in message
    assert str(then) not in message and str(now) not in message


def test_policy_output_is_validated():
    class BadPolicy(ConstantPolicy):
        def act(self, observations):
            return [12] * len(observations)

    with pytest.raises(ValueError, match="policy 'bad' returned action 12"):
        _run(BadPolicy("bad", 0), _episodes()[:1], batch=1)
    assert StepInfo(action=1).extra == {}


def test_max_episodes_subsample_is_evenly_spaced():
    from openfly_agent.eval.factory import subsample

    episodes = [make_episode(f"s/a/b/t{i}", [1, 0]) for i in range(10)]
    assert [e.episode_id for e in subsample(episodes, 3)] == ["s/a/b/t0", "s/a/b/t4", "s/a/b/t9"]
    assert subsample(episodes, None) == episodes and subsample(episodes, 50) == episodes


@pytest.mark.parametrize("root_exists", [False, True])
def test_a_missing_dataset_names_both_routes_to_one(root_exists, tmp_path):
    """Like train.py's missing root: generate it, or download the released data and pass its folder."""
    from openfly_agent.eval.factory import load_full_splits

    root = tmp_path / "data"
    if root_exists:
        root.mkdir()  # a folder without annotations: the reader's line names the file it looked for
    cfg = EvalConfig(policy="oracle", dataset_root=str(root), split=[C.SPLIT_TEST_SEEN])
    with pytest.raises(FileNotFoundError) as err:
        load_full_splits(cfg)
    message = str(err.value)
    first = "seen.json does not exist" if root_exists else f"dataset root {root} does not exist: "
    assert first in message and "\n" not in message
    assert message.endswith(
        f"generate it (python -m openfly_agent.toolchain generate --output_dir={root}), or download the released "
        "OpenFly data as data_cards/openfly_released.md says and pass its folder as --dataset_root"
    )

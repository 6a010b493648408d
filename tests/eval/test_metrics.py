"""Metrics under both profiles on hand-computed trajectories and the ground-truth replay of eval_test."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent.rollout.metrics import (
    OUTCOMES,
    EpisodeTrajectory,
    aggregate,
    dtw_distance,
    episode_metrics,
    episode_outcome,
    evaluate_profiles,
    ndtw,
    trajectory_from_actions,
)
from openfly_agent.rollout.profiles import OPENFLY, STANDARD, MetricProfile, get_profile
from openfly_agent.utils.geometry import Pose

START = Pose(0.0, 0.0, 0.0, 0.0)  # facing +x
GOAL = np.array([30.0, 0.0, 0.0])
STRAIGHT_REFERENCE = np.array([[0.0, 0, 0], [30.0, 0, 0]])  # length 30


def _traj(actions, collision_steps=(), goal=GOAL, reference=STRAIGHT_REFERENCE, scene="s"):
    return trajectory_from_actions("ep", scene, START, actions, goal, reference, collision_steps)


def test_profiles_are_registered_and_validated():
    assert get_profile("openfly") is OPENFLY and get_profile(STANDARD) is STANDARD
    with pytest.raises(KeyError, match="openfly"):
        get_profile("habitat")
    with pytest.raises(ValueError, match="collision_policy"):
        MetricProfile(name="bad", collision_policy="slide")
    with pytest.raises(ValueError, match="distance_dims"):
        MetricProfile(name="bad", distance_dims=1)
    assert OPENFLY.within(19.999) and not OPENFLY.within(20.0)
    assert MetricProfile(name="le", comparison="<=").within(20.0)


def test_openfly_spl_above_one_and_standard_clamps():
    # forward 9, forward 3, STOP: positions x = 0, 9, 12, 12; NE = 18.
    m_of = episode_metrics(_traj([9, 1, 0]), OPENFLY)
    m_st = episode_metrics(_traj([9, 1, 0]), STANDARD)
    for m in (m_of, m_st):
        assert m["ne"] == pytest.approx(18.0)
        assert m["success"] and m["oracle_success"] and m["stopped"]
        assert m["path_length"] == pytest.approx(12.0)
        assert m["steps"] == 3
    assert m_of["spl"] == pytest.approx(30.0 / 12.001)  # straight line / (P + 1e-3), no clamp
    assert m_of["spl"] > 1.0
    assert m_st["spl"] == pytest.approx(1.0)  # 30 / max(12, 30)


def test_collision_inside_success_radius():
    # x = 0, 9, 18, 21, 21; the move of action 2 (18 -> 21) collides, both ends inside 20 m of the goal.
    traj = _traj([9, 9, 1, 0], collision_steps=[2])
    m_of = episode_metrics(traj, OPENFLY)
    assert m_of["success"] and m_of["ne"] == pytest.approx(9.0)
    assert m_of["collided"] and m_of["num_collisions"] == 1 and not m_of["ended_by_collision"]
    assert m_of["spl"] == pytest.approx(30.0 / 21.001)
    m_st = episode_metrics(traj, STANDARD)
    assert not m_st["success"] and m_st["spl"] == 0.0
    assert m_st["ended_by_collision"] and m_st["collided"] and not m_st["stopped"]
    assert m_st["ne"] == pytest.approx(12.0)  # ends before the colliding move, at x = 18
    assert m_st["path_length"] == pytest.approx(18.0)
    assert m_st["steps"] == 3 and m_st["oracle_success"]
    counting = MetricProfile(
        name="count",
        stop_required=True,
        collision_policy="count",
        spl_clamp=True,
        spl_reference="reference_path",
    )
    m_count = episode_metrics(traj, counting)
    assert m_count["success"] and m_count["num_collisions"] == 1 and m_count["spl"] == pytest.approx(1.0)


def test_stop_outside_the_radius_fails_everywhere():
    traj = _traj([1, 0])  # x = 0, 3, 3: NE 27
    for profile in (OPENFLY, STANDARD):
        m = episode_metrics(traj, profile)
        assert m["ne"] == pytest.approx(27.0)
        assert not m["success"] and not m["oracle_success"] and m["spl"] == 0.0 and m["stopped"]


def test_oracle_pass_that_never_stops():
    # x = 0, 9, ..., 54: passes 3 m from the goal at x = 27, ends 24 m past it, never stops.
    traj = _traj([9] * 6)
    for profile in (OPENFLY, STANDARD):
        m = episode_metrics(traj, profile)
        assert m["oracle_success"] and not m["success"] and not m["stopped"]
        assert m["ne"] == pytest.approx(24.0) and m["steps"] == 6


def test_ending_inside_without_stop_counts_only_for_openfly():
    traj = _traj([9, 9, 9])  # x = 27, NE 3, no STOP
    assert episode_metrics(traj, OPENFLY)["success"]
    assert episode_metrics(traj, OPENFLY)["spl"] == pytest.approx(30.0 / 27.001)
    assert not episode_metrics(traj, STANDARD)["success"]


def test_stop_at_start_within_radius_is_the_official_spl_blow_up():
    # The official pass_len starts at 1e-3, so an immediate STOP near the goal scores L / 0.001.
    traj = _traj([0], goal=[10.0, 0, 0], reference=[[0.0, 0, 0], [10.0, 0, 0]])
    m_of = episode_metrics(traj, OPENFLY)
    assert m_of["success"] and m_of["oracle_success"] and m_of["spl"] == pytest.approx(10.0 / 0.001)
    m_st = episode_metrics(traj, STANDARD)
    assert m_st["success"] and m_st["spl"] == pytest.approx(1.0)


def test_step_budget_truncates_and_a_late_stop_does_not_count():
    goal = [300.0, 0, 0]
    reference = [[0.0, 0, 0], [300.0, 0, 0]]
    long_run = _traj([1] * 120, goal=goal, reference=reference)  # x = 300 after 100 steps, 360 after 120
    m = episode_metrics(long_run, OPENFLY)
    assert m["steps"] == 100 and m["ne"] == pytest.approx(0.0) and m["success"]
    late_stop = _traj([1] * 100 + [0], goal=goal, reference=reference)  # STOP is the 101st action
    assert not episode_metrics(late_stop, STANDARD)["stopped"]
    assert not episode_metrics(late_stop, STANDARD)["success"]
    on_time = _traj([1] * 99 + [0], goal=[297.0, 0, 0], reference=[[0.0, 0, 0], [297.0, 0, 0]])
    assert episode_metrics(on_time, STANDARD)["success"]


def test_two_dimensional_profile_ignores_altitude():
    traj = _traj([0], goal=[20.0, 0.0, 100.0], reference=[[0.0, 0, 0], [20.0, 0, 100]])
    aerialvln_like = MetricProfile(
        name="aerialvln", distance_dims=2, comparison="<=", osr_includes_start=True
    )
    m = episode_metrics(traj, aerialvln_like)
    assert m["ne"] == pytest.approx(20.0) and m["success"] and m["oracle_success"]
    assert not episode_metrics(traj, OPENFLY)["success"]  # 3-D distance is ~102 m


def test_dtw_hand_value_and_ndtw():
    query = np.array([[0.0, 0], [1, 0], [2, 0]])
    reference = np.array([[0.0, 0], [2, 0]])
    assert dtw_distance(query, reference) == pytest.approx(1.0)
    assert ndtw(query, reference, 20.0) == pytest.approx(math.exp(-1.0 / 40.0))
    # consecutive duplicates are dropped before matching (turns repeat positions)
    assert ndtw(np.repeat(query, 3, axis=0), reference, 20.0) == pytest.approx(math.exp(-1.0 / 40.0))


def _naive_dtw(a: np.ndarray, b: np.ndarray) -> float:
    table = np.full((len(a) + 1, len(b) + 1), np.inf)
    table[0, 0] = 0.0
    for i in range(1, len(a) + 1):
        for j in range(1, len(b) + 1):
            cost = float(np.linalg.norm(a[i - 1] - b[j - 1]))
            table[i, j] = cost + min(table[i - 1, j], table[i, j - 1], table[i - 1, j - 1])
    return float(table[-1, -1])


_paths = st.lists(st.tuples(*[st.floats(-50, 50, allow_nan=False)] * 3), min_size=1, max_size=12)


@settings(max_examples=60, deadline=None)
@given(_paths, _paths)
def test_dtw_matches_the_textbook_recursion(a, b):
    a, b = np.array(a), np.array(b)
    assert dtw_distance(a, b) == pytest.approx(_naive_dtw(a, b), rel=1e-9, abs=1e-9)


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.sampled_from([0, 1, 2, 3, 4, 5, 6, 7, 8, 9]), min_size=1, max_size=30),
    st.tuples(st.floats(-60, 60), st.floats(-60, 60), st.floats(-20, 20)),
)
def test_metric_invariants_on_random_rollouts(actions, goal):
    traj = _traj(actions, goal=list(goal), reference=[[0.0, 0, 0], list(goal)])
    for profile in (OPENFLY, STANDARD):
        m = episode_metrics(traj, profile)
        if m["success"]:
            assert m["oracle_success"]
        assert 0.0 <= m["ndtw"] <= 1.0 and m["sdtw"] <= m["ndtw"]
    assert 0.0 <= episode_metrics(traj, STANDARD)["spl"] <= 1.0


def test_aggregate_per_scene_overall_and_scene_mean():
    rows = [
        episode_metrics(_traj([9, 1, 0], scene="a"), STANDARD),  # success, spl 1
        episode_metrics(_traj([1, 0], scene="a"), STANDARD),  # fail
        episode_metrics(_traj([9, 9, 1, 0], collision_steps=[2], scene="b"), STANDARD),  # collision fail
    ]
    result = aggregate(rows)
    assert result["profile"] == "standard"
    overall = result["overall"]
    assert overall["episodes"] == 3
    assert overall["sr_pct"] == pytest.approx(100 / 3)
    assert overall["ne_m"] == pytest.approx((18 + 27 + 12) / 3)
    assert overall["spl_pct"] == pytest.approx(100 / 3)
    assert overall["collision_rate_pct"] == pytest.approx(100 / 3)
    # Counts and 95 % intervals. Wilson, 1 of 3: z^2/n = 1.280486, centre = (0.333333 + 0.640243) / 2.280486
    # = 0.426916, half = 1.959964 * sqrt(0.074074 + 0.106707) / 2.280486 = 0.365424 -> 6.15 .. 79.23 %;
    # 2 of 3 (OSR: the collision path came within 12 m) mirrors it.
    assert (overall["successes"], overall["oracle_successes"]) == (1, 2)
    assert overall["sr_ci95"] == pytest.approx([6.1492, 79.2340], abs=1e-3)
    assert overall["osr_ci95"] == pytest.approx([20.7660, 93.8508], abs=1e-3)
    # Bootstrap of 3 values: a resample repeats one value with probability 1/27 = 3.7 % > 2.5 %, so the
    # interval runs from the smallest value to the largest: NE 12 .. 27 m, SPL 0 .. 100 %.
    assert overall["ne_ci95"] == [12.0, 27.0] and overall["spl_ci95"] == [0.0, 100.0]
    assert "sr_ci95" not in aggregate(rows)["scene_mean"]  # a mean of scenes has no interval
    assert result["per_scene"]["a"]["sr_pct"] == pytest.approx(50.0)
    assert result["per_scene"]["b"]["episodes"] == 1 and result["per_scene"]["b"]["sr_pct"] == 0.0
    assert result["scene_mean"]["sr_pct"] == pytest.approx(25.0)  # unweighted over scenes
    assert set(aggregate(rows, by=None)) == {"profile", "overall"}
    with pytest.raises(ValueError, match="several profiles"):
        aggregate(rows + [episode_metrics(_traj([0]), OPENFLY)])
    with pytest.raises(ValueError, match="no episodes"):
        aggregate([])


@pytest.mark.parametrize(
    ("actions", "collisions", "standard", "openfly"),
    [
        ([9, 1, 0], (), "success", "success"),  # x = 12, NE 18, STOP as action 2: a success is never early
        ([0], (), "early_stop", "early_stop"),  # STOP as action 0 at the start, NE 30
        ([1, 0], (), "early_stop", "early_stop"),  # x = 3, NE 27, STOP as action 1
        ([1, 1, 1, 0], (), "stopped_far", "stopped_far"),  # x = 9, NE 21: never within 20 m, STOP as action 3
        ([9] * 6 + [0], (), "stopped_after_passing", "stopped_after_passing"),  # x = 27 (NE 3) ... 54 (NE 24)
        ([9, 9, 1, 0], (2,), "collision_end", "success"),  # openfly ignores the collision
        ([9], (), "step_limit", "step_limit"),  # x = 9, NE 21, no STOP
        ([9, 9], (), "step_limit", "success"),  # x = 18, NE 12: openfly needs no STOP
    ],
)
def test_episode_outcome_of_hand_built_flights(actions, collisions, standard, openfly):
    traj = _traj(actions, collision_steps=collisions)
    for profile, expected in ((STANDARD, standard), (OPENFLY, openfly)):
        row = episode_metrics(traj, profile)
        assert row["outcome"] == expected, profile.name
        assert row["success"] == (expected == "success")
        flags = ("early_stop", "stopped_far", "stopped_after_passing", "step_limit")
        assert [row[flag] for flag in flags] == [expected == flag for flag in flags]


def test_outcome_rates_sum_to_one_hundred_with_sr():
    rows = [
        episode_metrics(_traj(actions, collision_steps=c), STANDARD)
        for actions, c in (
            ([9, 1, 0], ()),
            ([1, 0], ()),
            ([1, 1, 1, 0], ()),
            ([1, 1, 1, 0], ()),
            ([9, 9, 1, 0], (2,)),
            ([9], ()),
        )
    ]
    overall = aggregate(rows)["overall"]
    assert overall["sr_pct"] == pytest.approx(100 / 6) and overall["stopped_far_pct"] == pytest.approx(
        200 / 6
    )
    assert overall["early_stop_pct"] == pytest.approx(100 / 6)
    assert overall["collision_end_pct"] == pytest.approx(100 / 6)
    assert overall["step_limit_pct"] == pytest.approx(100 / 6)
    assert overall["stopped_after_passing_pct"] == 0.0
    rates = (
        "sr_pct",
        "early_stop_pct",
        "stopped_far_pct",
        "stopped_after_passing_pct",
        "collision_end_pct",
        "step_limit_pct",
    )
    assert len(rates) == len(OUTCOMES) and sum(overall[k] for k in rates) == pytest.approx(100.0)


@given(
    success=st.booleans(),
    stopped=st.booleans(),
    oracle=st.booleans(),
    collision_end=st.booleans(),
    stop_step=st.one_of(st.none(), st.integers(0, 10)),
)
def test_every_flag_combination_has_exactly_one_outcome(success, stopped, oracle, collision_end, stop_step):
    outcome = episode_outcome(success, stopped, oracle, collision_end, stop_step)
    assert outcome in OUTCOMES
    assert (outcome == "success") == success
    early = stopped and not success and not collision_end and stop_step is not None and stop_step < 3
    assert (outcome == "early_stop") == early


def test_bad_trajectories_name_the_episode_and_field():
    with pytest.raises(ValueError, match="ep7.*positions"):
        EpisodeTrajectory("ep7", "s", np.zeros((3, 2)), GOAL, STRAIGHT_REFERENCE)
    with pytest.raises(ValueError, match="ep7: stop_step 5"):
        EpisodeTrajectory("ep7", "s", np.zeros((3, 3)), GOAL, STRAIGHT_REFERENCE, stop_step=5)
    with pytest.raises(ValueError, match="cannot collide"):
        EpisodeTrajectory(
            "ep7", "s", np.zeros((3, 3)), GOAL, STRAIGHT_REFERENCE, stop_step=1, collision_step=1
        )
    traj = _traj([1, 9, 9], collision_steps=[2])
    assert traj.collision_step == 2 and traj.collision_steps == (2,)
    assert _traj([1, 0, 9, 9]).num_actions == 2  # actions after STOP are dropped


def _eval_test_trajectories(path) -> list[EpisodeTrajectory]:
    """Minimal parse of the official annotation: positions (3 or 4 numbers), goal = last position."""
    records = json.loads(path.read_text())
    trajectories = []
    for record in records:
        positions = np.array([p[:3] for p in record["pos"]], dtype=np.float64)
        trajectories.append(
            EpisodeTrajectory(
                episode_id=record["image_path"],
                scene_id=record["image_path"].split("/")[0],
                positions=positions,
                goal=positions[-1],
                reference_path=positions,
                stopped=True,
            )
        )
    return trajectories


def test_ground_truth_replay_of_eval_test_is_perfect(openfly_fixtures):
    trajectories = _eval_test_trajectories(openfly_fixtures / "eval_test.json")
    assert len(trajectories) == 240
    records = json.loads((openfly_fixtures / "eval_test.json").read_text())
    assert any(len(p) == 4 for r in records for p in r["pos"])  # some entries carry a yaw
    results = evaluate_profiles(trajectories)
    assert set(results) == {"openfly", "standard"}
    for name, result in results.items():
        overall = result["overall"]
        assert overall["episodes"] == 240, name
        assert overall["sr_pct"] == 100.0 and overall["osr_pct"] == 100.0, name
        assert overall["ne_m"] == 0.0, name
        assert overall["ndtw_pct"] == pytest.approx(100.0), name
        assert len(result["per_scene"]) == 8
        assert all(s["episodes"] == 30 and s["sr_pct"] == 100.0 for s in result["per_scene"].values())
    assert results["standard"]["overall"]["spl_pct"] == pytest.approx(100.0)
    # openfly SPL = straight line / (GT path + 1e-3) <= 1 on replayed ground truth
    assert 0.0 < results["openfly"]["overall"]["spl_pct"] < 100.0


def test_stop_at_once_baseline_matches_the_published_per_scene_rates(openfly_fixtures):
    """STOP at step 0 succeeds on 26/240 eval_test episodes, per scene as docs/OFFICIAL_OPENFLY.md 6.2."""
    trajectories = []
    for gt in _eval_test_trajectories(openfly_fixtures / "eval_test.json"):
        start = gt.positions[0]
        trajectories.append(
            EpisodeTrajectory(
                gt.episode_id, gt.scene_id, [start, start], gt.goal, gt.reference_path, stop_step=0
            )
        )
    results = evaluate_profiles(trajectories)
    expected_sr = {
        "env_airsim_16": 10.0,
        "env_airsim_18": 13.3,
        "env_airsim_23": 6.7,
        "env_airsim_26": 3.3,
        "env_airsim_sh": 0.0,
        "env_airsim_gz": 10.0,
        "env_ue_smallcity": 16.7,
        "env_ue_bigcity": 26.7,
    }
    for result in results.values():
        assert result["overall"]["sr_pct"] == pytest.approx(100 * 26 / 240)
        assert result["overall"]["ne_m"] == pytest.approx(74.2, abs=0.05)  # mean straight-line start -> goal
        per_scene = {scene: round(s["sr_pct"], 1) for scene, s in result["per_scene"].items()}
        assert per_scene == expected_sr
    assert results["standard"]["overall"]["spl_pct"] == pytest.approx(100 * 26 / 240)  # L / max(0, L) = 1
    assert results["openfly"]["overall"]["spl_pct"] > 10_000  # L / 0.001 for the 26 successes

"""A* in the action space, conversion to the codebook, replay through the dynamics, route sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from toolchain_scene import BOUNDS, synthetic_scene

from openfly_agent import constants as C
from openfly_agent.sim import dynamics
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.toolchain.actions import (
    build_action_sequence,
    camera_pitch_for,
    categorize,
    merge_forward,
    navigation_mask,
    sequence_category,
)
from openfly_agent.toolchain.astar import ActionSpaceAStar, PlanningFailed, turns_between
from openfly_agent.toolchain.config import CategoryConfig, MapConfig, PlannerConfig, RouteConfig
from openfly_agent.toolchain.routes import RouteSampler, RouteSamplingFailed
from openfly_agent.toolchain.voxel_map import build_planning_map
from openfly_agent.utils.geometry import Pose

MAP_CFG = MapConfig(voxel_size_m=2.0, dilate_radius_m=3.0, min_height_thresh_m=5.0)


@pytest.fixture(scope="module")
def scene():
    points, landmarks, truth = synthetic_scene()
    return build_planning_map(points, MAP_CFG, BOUNDS, 0.0), landmarks, truth


def _open_map(size=60.0):
    return build_planning_map(
        np.zeros((0, 3)),
        MapConfig(voxel_size_m=2.0, min_height_thresh_m=5.0),
        SceneBounds(-size, size, -size, size, 0, 60),
        0.0,
    )


def test_merge_forward_blocks_of_three_then_remainder():
    assert merge_forward([1, 1, 1, 1, 1, 2, 1]) == ([9, 8, 2, 1], [0, 3, 5, 6])
    assert merge_forward([1, 1, 1, 1]) == ([9, 1], [0, 3])
    assert merge_forward([2, 3, 0]) == ([2, 3, 0], [0, 1, 2])


def test_turns_between_takes_the_short_way():
    assert turns_between(0, 1) == 1 and turns_between(0, 11) == -1
    assert turns_between(3, 0) == -3 and turns_between(0, 6) == 6 and turns_between(10, 2) == 4


@settings(max_examples=40, deadline=None)
@given(
    prims=st.lists(st.sampled_from([1, 2, 3, 4, 5]), min_size=0, max_size=40),
    takeoff=st.integers(0, 3),
    landing=st.integers(0, 3),
    yaw=st.floats(-math.pi, math.pi),
)
def test_action_sequence_replays_exactly(prims, takeoff, landing, yaw):
    start = Pose(1.0, -2.0, 30.0, yaw)
    seq = build_action_sequence(start, prims, takeoff, landing)
    # every label but the last is executed: positions / yaws of the next frame are exactly the dynamics'
    for t in range(len(seq) - 1):
        nxt = dynamics.apply_action(seq.poses[t], int(seq.actions[t]))
        assert (nxt.x, nxt.y, nxt.z, nxt.yaw) == (*seq.positions[t + 1], seq.yaws[t + 1])
    assert (seq.actions == C.ACTION_STOP).sum() == 1
    stop = int(np.flatnonzero(seq.actions == C.ACTION_STOP)[0])
    assert seq.actions[:takeoff].tolist() == [C.ACTION_TAKEOFF] * takeoff
    assert seq.actions[stop + 1 :].tolist() == [C.ACTION_LANDING] * (landing + 1 if landing else 0)
    # the merged labels travel as far as the primitives: the STOP pose equals the primitive replay's end
    raw_end = dynamics.rollout(start, [C.ACTION_ASCEND] * takeoff + prims)[-1]
    assert np.allclose(seq.positions[stop], raw_end.position, atol=1e-9)
    assert seq.raw_index[-1] == takeoff + len(prims) + (landing + 1 if landing else 0)
    if landing:  # the landed frame is `landing` descents below the STOP pose
        assert seq.positions[-1][2] == pytest.approx(seq.positions[stop][2] - C.STEP_METERS * landing)


def test_navigation_mask_and_categories():
    actions = np.array([-1, -1, 9, 2, 0, -2, -2])
    assert navigation_mask(actions).tolist() == [False, False, True, True, True, False, False]
    cfg = CategoryConfig(height_bins_m=[30, 60], length_bins_m=[100, 200])
    assert categorize(10, 50, cfg) == "low_short"
    assert categorize(30, 100, cfg) == "medium_average"
    assert categorize(75, 250, cfg, updown=True) == "high_long_updown"
    seq = build_action_sequence(Pose(0, 0, 40, 0), [1] * 40)  # 120 m at 40 m
    assert sequence_category(seq, 0.0, cfg) == "medium_average"
    assert camera_pitch_for("high_short") == C.HIGH_CATEGORY_PITCH_DEG and camera_pitch_for("low_long") == 0.0


def test_astar_straight_line_in_free_space_is_all_forward():
    astar = ActionSpaceAStar(_open_map(), PlannerConfig())
    start = Pose(-45.0, 0.0, 20.0, 0.0)
    result = astar.plan(start, np.array([45.0, 0.0, 20.0]))
    assert set(result.primitives) == {C.ACTION_FORWARD}
    assert len(result.primitives) == 29  # 87 m: within 3.1 m of the goal after 29 steps of 3 m
    seq = build_action_sequence(start, result.primitives)
    assert seq.actions.tolist() == [9] * 9 + [8, 0]
    assert np.linalg.norm(seq.positions[-1] - [45.0, 0.0, 20.0]) <= 3.1


def test_astar_turns_toward_a_goal_behind_and_climbs():
    astar = ActionSpaceAStar(_open_map(), PlannerConfig())
    start = Pose(0.0, 0.0, 20.0, 0.0)
    result = astar.plan(start, np.array([-30.0, 0.0, 35.0]))
    # a U-turn (6 turns, either way) plus the climbs that bring it within 3.1 m of the 15 m higher goal
    turns = [p for p in result.primitives if p in (C.ACTION_TURN_LEFT, C.ACTION_TURN_RIGHT)]
    assert len(turns) == 6 and len(set(turns)) == 1
    assert result.primitives.count(C.ACTION_ASCEND) in (4, 5)
    assert C.ACTION_DESCEND not in result.primitives
    end = dynamics.rollout(start, result.primitives)[-1]
    assert np.linalg.norm(end.position - [-30.0, 0.0, 35.0]) <= 3.1


def test_astar_goes_around_a_building_without_collision(scene):
    pmap, _, truth = scene
    astar = ActionSpaceAStar(pmap, PlannerConfig())
    start, goal = Pose(-60.0, 0.0, 20.0, 0.0), np.array([60.0, 0.0, 20.0])  # the 60 m tower is in between
    result = astar.plan(start, goal)
    seq = build_action_sequence(start, result.primitives)
    assert any(a in (C.ACTION_TURN_LEFT, C.ACTION_TURN_RIGHT) for a in seq.actions)
    for a, b in zip(seq.positions[:-1], seq.positions[1:]):
        assert not truth.segment_collides(a, b, ground_z=0.0)
    assert np.linalg.norm(seq.positions[-1] - goal) <= 3.1


def test_astar_fails_clearly(scene):
    pmap, _, _ = scene
    astar = ActionSpaceAStar(pmap, PlannerConfig(max_expansions=5))
    with pytest.raises(PlanningFailed) as err:
        astar.plan(Pose(-60.0, 0.0, 20.0, 0.0), np.array([60.0, 0.0, 20.0]))
    assert err.value.reason == "max_expansions"
    with pytest.raises(PlanningFailed) as err:
        ActionSpaceAStar(pmap).plan(Pose(-19.0, 0.0, 20.0, 0.0), np.array([60.0, 0.0, 20.0]))  # at a wall
    assert err.value.reason == "start_blocked"
    with pytest.raises(PlanningFailed) as err:
        ActionSpaceAStar(pmap).plan(Pose(-60.0, 0.0, 20.0, 0.0), np.array([60.0, 0.0, 2.0]))  # too low
    assert err.value.reason == "goal_blocked"


def test_astar_reports_no_path_when_walled_in():
    # a closed 30 m square of 60 m walls; the map ends at 62 m, so the drone cannot climb over them
    side = range(-15, 16, 1)
    points = np.array(
        [[x, y, z] for x in side for z in range(0, 61, 2) for y in (-15.0, 15.0)]
        + [[x, y, z] for y in side for z in range(0, 61, 2) for x in (-15.0, 15.0)],
        float,
    )
    pmap = build_planning_map(
        points,
        MapConfig(voxel_size_m=2.0, dilate_radius_m=3.0, min_height_thresh_m=5.0),
        SceneBounds(-60, 60, -60, 60, 0, 62),
        0.0,
    )
    with pytest.raises(PlanningFailed) as err:
        ActionSpaceAStar(pmap).plan(Pose(0.0, 0.0, 20.0, 0.0), np.array([50.0, 50.0, 20.0]))
    assert err.value.reason == "no_path"


def test_routes_respect_ring_height_footprint_and_are_plannable(scene):
    pmap, landmarks, truth = scene
    cfg = RouteConfig(height_min_m=5, height_max_m=25, min_dist_m=60, max_dist_m=90)
    sampler, astar = RouteSampler(pmap, landmarks, cfg), ActionSpaceAStar(pmap)
    rng = np.random.default_rng(0)
    by_id = {lm.landmark_id: lm for lm in landmarks}
    for _ in range(8):
        route = sampler.sample(rng)
        leg = route.legs[0]
        centre = np.array(by_id[leg.landmark.landmark_id].position[:2])
        assert 60 <= np.linalg.norm(route.start.position[:2] - centre) <= 90
        assert 10 <= route.flight_z <= 30 and route.start.z == route.flight_z == leg.goal[2]
        assert not pmap.bev_blocked(leg.goal[None, :2])[0] and pmap.is_free(leg.goal[None])[0]
        assert np.linalg.norm(leg.goal - route.start.position) >= cfg.min_goal_dist_m
        assert not truth.is_occupied(leg.goal[None])[0]
        result = astar.plan(route.start, leg.goal)
        seq = build_action_sequence(route.start, result.primitives)
        assert all(
            not truth.segment_collides(a, b, 0.0) for a, b in zip(seq.positions[:-1], seq.positions[1:])
        )


def test_chained_routes_turn_between_legs(scene):
    pmap, landmarks, _ = scene
    cfg = RouteConfig(height_min_m=5, height_max_m=10, min_dist_m=60, max_dist_m=160, chain_prob=1.0)
    route = RouteSampler(pmap, landmarks, cfg).sample(np.random.default_rng(3))
    assert len(route.legs) == 2 and route.landmark_ids[0] != route.landmark_ids[1]
    first = math.atan2(*(route.legs[0].goal[1::-1] - route.start.position[1::-1]))
    second = math.atan2(*(route.legs[1].goal[1::-1] - route.legs[0].goal[1::-1]))
    change = abs(math.degrees((second - first + math.pi) % (2 * math.pi) - math.pi))
    assert 20 <= change <= 160  # landmark bearing within 30-150 deg; the goals sit a little off the centres


def test_with_turn_routes_are_blocked_in_a_straight_line(scene):
    pmap, landmarks, _ = scene
    cfg = RouteConfig(height_min_m=5, height_max_m=10, min_dist_m=60, max_dist_m=150, with_turn_prob=1.0)
    sampler = RouteSampler(pmap, landmarks, cfg)
    rng = np.random.default_rng(1)
    routes = []
    for _ in range(20):
        try:
            routes.append(sampler.sample(rng))
        except RouteSamplingFailed:
            continue
    assert routes, "some start behind a building must exist"
    for route in routes:
        line = route.start.position + np.linspace(0, 1, 200)[:, None] * (
            route.legs[0].goal - route.start.position
        )
        assert not pmap.is_free(line).all()


def test_sampling_fails_clearly_when_no_landmark_is_tall_enough(scene):
    pmap, landmarks, _ = scene
    cfg = RouteConfig(height_min_m=80, height_max_m=90, min_dist_m=60, max_dist_m=90)
    with pytest.raises(RouteSamplingFailed, match="no landmark reaches"):
        RouteSampler(pmap, landmarks, cfg).sample(np.random.default_rng(0))


def test_heuristic_counts_the_turns_any_path_still_needs():
    astar = ActionSpaceAStar(_open_map(), PlannerConfig(heuristic_weight=1.0, turn_penalty=2.0))
    yaws = [math.radians(30 * h) for h in range(12)]
    h = astar._heuristic(yaws, (0.0, 60.0, 20.0))  # goal 90 deg to the left of heading 0
    assert h(0.0, 0.0, 20.0, 0) == pytest.approx(60.0 + 2.0 * 3)  # ceil((90 - asin(3.1 / 60)) / 30) = 3
    assert h(0.0, 0.0, 20.0, 3) == pytest.approx(60.0)  # already facing it
    assert h(0.0, -60.0, 20.0, 9) == pytest.approx(120.0 + 2.0 * 6)  # heading away from it: a U-turn
    assert h(0.0, 0.0, 20.0 + 80.0, 0) == pytest.approx(math.hypot(60.0, 80.0) + 6.0)
    assert h(0.0, 58.0, 20.0, 7) == pytest.approx(2.0)  # within tolerance horizontally: no turn needed


@pytest.mark.parametrize("landmarks", [[1, 2], [4, 3], [3]])
def test_chain_landmarks_must_be_a_range_from_two(landmarks):
    with pytest.raises(ValueError, match="route.chain_landmarks"):
        RouteConfig(chain_landmarks=landmarks)

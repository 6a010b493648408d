"""Collisions of motion segments with buildings and the ground, and the three policies of the simulator."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.city import CityConfig, generate_city
from openfly_agent.sim.collision import motion_collides, segments_collide
from openfly_agent.sim.dynamics import step_motion
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.utils.geometry import Pose

from .scenes import tower_city

TINY_CITY = generate_city(9, CityConfig(size_m=300.0, n_buildings=30, n_trees=40))
FACING_TOWER = Pose(78.0, 0.0, 50.0, 0.0)  # 12 m west of the tower's west face (x = 90), heading east


def test_flying_into_the_tower_collides_on_the_step_that_reaches_its_voxels():
    grid = tower_city().occupancy(2.0)
    pose, hits = FACING_TOWER, []
    for _ in range(5):
        motion = step_motion(pose, C.ACTION_FORWARD)
        hits.append(motion_collides(grid, motion, ground_z=0.0))
        pose = motion.end
    # x: 78 -> 81 -> 84 -> 87 -> 90: the fourth step enters voxel [90, 92), the tower's first
    assert hits == [False, False, False, True, True]
    assert motion_collides(grid, step_motion(Pose(84.0, 0.0, 50.0, 0.0), C.ACTION_FORWARD_9))
    assert not motion_collides(
        grid, step_motion(Pose(84.0, 0.0, 102.0, 0.0), C.ACTION_FORWARD_9)
    )  # above roof


def test_the_ground_counts_as_an_obstacle():
    grid = tower_city().occupancy(2.0)
    assert not motion_collides(grid, step_motion(Pose(0, 0, 4.0, 0), C.ACTION_DESCEND))  # 4 -> 1 m
    assert motion_collides(grid, step_motion(Pose(0, 0, 3.0, 0), C.ACTION_DESCEND))  # touches z = 0
    assert not motion_collides(grid, step_motion(Pose(0, 0, 3.0, 0), C.ACTION_DESCEND), ground_z=None)
    assert not motion_collides(grid, step_motion(Pose(0, 0, -5.0, 0), C.ACTION_STOP))  # STOP never collides


@settings(max_examples=25, deadline=None)
@given(
    starts=st.lists(st.tuples(*[st.floats(-160, 160)] * 2, st.floats(-5, 80)), min_size=1, max_size=20),
    moves=st.lists(st.tuples(*[st.floats(-30, 30)] * 3), min_size=20, max_size=20),
)
def test_vectorised_check_agrees_with_the_grid_one(starts, moves):
    grid = TINY_CITY.occupancy(2.0)
    a = np.array(starts)
    b = a + np.array(moves)[: len(a)]
    expected = [grid.segment_collides(s, e, ground_z=0.0) for s, e in zip(a, b)]
    assert segments_collide(grid, a, b, ground_z=0.0).tolist() == expected


@pytest.fixture(scope="module")
def sims():
    made = {}

    def make(policy):
        if policy not in made:
            made[policy] = EmbeddedSimulator(EmbeddedSimConfig(width=32, height=32, collision=policy))
            made[policy].register_city(tower_city())
        return made[policy]

    yield make
    for sim in made.values():
        sim.close()


def _fly(sim, n):
    sim.reset(EpisodeSpec("e", "test-tower", FACING_TOWER))
    return [sim.step(C.ACTION_FORWARD)[1] for _ in range(n)]


def test_policy_end_blocks_the_move_and_ends_the_episode(sims):
    sim = sims("end")
    infos = _fly(sim, 4)
    assert [i.collided for i in infos] == [False, False, False, True] and infos[-1].done
    assert sim.pose == Pose(87.0, 0.0, 50.0, 0.0)  # stays in front of the wall
    assert infos[-1].extra["attempted_pose"].x == pytest.approx(90.0)
    with pytest.raises(RuntimeError, match="has ended"):
        sim.step(C.ACTION_FORWARD)


def test_policy_count_flags_and_moves_on(sims):
    sim = sims("count")
    infos = _fly(sim, 6)
    assert [i.collided for i in infos] == [False, False, False, True, True, True]
    assert not any(i.done for i in infos) and infos[-1].extra["collisions"] == 3
    assert sim.pose.x == pytest.approx(96.0)


def test_policy_ignore_never_checks(sims):
    sim = sims("ignore")
    infos = _fly(sim, 6)
    assert not any(i.collided for i in infos) and not any(i.done for i in infos)

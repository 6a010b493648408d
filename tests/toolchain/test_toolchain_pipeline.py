"""Planning stage of the pipeline on a tiny embedded city, scene sources, work units, shards, ledger."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from toolchain_scene import BUILDINGS, box_surface_points

from openfly_agent import constants as C
from openfly_agent.sim import dynamics
from openfly_agent.sim.city import generate_city
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.pointcloud import write_points
from openfly_agent.sim.real_scene import read_landmark_list, read_scene_config
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.toolchain.config import (
    VAL_INDEX_BASE,
    CategoryConfig,
    GenerateConfig,
    RenderConfig,
    RouteConfig,
    SceneConfig,
)
from openfly_agent.toolchain.generate import (
    ROLE_TRAIN,
    ROLE_UNSEEN,
    ROLE_VAL,
    pending_units,
    scene_units,
    shard_scenes,
)
from openfly_agent.toolchain.landmarks import write_landmark_list
from openfly_agent.toolchain.ledger import UnitLedger
from openfly_agent.toolchain.pipeline import (
    KIND_ASTAR,
    KIND_DAGGER,
    Rejected,
    WorkUnit,
    build_episode,
    plan_trajectory,
    prepare_scene,
)
from openfly_agent.toolchain.render import RenderedFrames, leg_of_frame, leg_target_boxes, target_boxes
from openfly_agent.toolchain.routes import RouteSampler
from openfly_agent.toolchain.scenes import (
    city_config_for,
    embedded_scene,
    generate_config_for_real_scene,
    map_config_for,
    real_scene,
    route_config_for,
)
from openfly_agent.toolchain.summary import summarize_records
from openfly_agent.toolchain.voxel_map import dilate_grid

TINY = SceneConfig(
    city_size_m=300, city_buildings=30, train_seeds=[0, 2], unseen_seeds=[1], trajectories_per_scene=10
)


def tiny_config(scenes: SceneConfig = TINY, **kw) -> GenerateConfig:
    route = RouteConfig(
        height_min_m=10, height_max_m=40, min_dist_m=40, max_dist_m=90,
        with_turn_prob=0.3, chain_prob=0.3, takeoff_landing_prob=0.3,
    )  # fmt: skip
    categories = CategoryConfig(height_bins_m=[25, 40], length_bins_m=[50, 100])
    return GenerateConfig(scenes=scenes, route=route, categories=categories, **kw)


@pytest.fixture(scope="module")
def prepared():
    return prepare_scene(embedded_scene(0, TINY), tiny_config())


def test_embedded_scene_matches_the_city(prepared):
    city = generate_city(0, city_config_for(TINY))
    assert prepared.scene.scene_id == "embedded-0"
    assert set(prepared.landmarks) == {lm.landmark_id for lm in city.landmarks}
    assert prepared.tree_height_m == pytest.approx(max(t.height_m for t in city.trees))
    # every building's roof is in the map built from the point cloud
    for b in city.buildings[:10]:
        body = b.parts[0]  # the main block: its roof surface is sampled by the point cloud
        roof = np.array([[(body.lo[0] + body.hi[0]) / 2, (body.lo[1] + body.hi[1]) / 2, body.hi[2] + 0.01]])
        assert prepared.pmap.grid.is_occupied(roof)[0]


def test_planned_trajectories_replay_without_collision_and_reach_their_goal(prepared):
    city = generate_city(0, city_config_for(TINY))
    truth = city.occupancy(1.0)
    cfg, seen_updown, seen_chain = tiny_config(), False, False
    for seed in range(25):
        try:
            planned = plan_trajectory(prepared, np.random.default_rng(seed), cfg)
        except Rejected as err:
            assert err.reason in ("no_route", "astar_max_expansions", "astar_no_path")
            continue
        seq = planned.seq
        for t in range(len(seq) - 1):
            nxt = dynamics.apply_action(seq.poses[t], int(seq.actions[t]))
            assert (nxt.x, nxt.y, nxt.z, nxt.yaw) == (*seq.positions[t + 1], seq.yaws[t + 1])
            assert not truth.segment_collides(seq.positions[t], seq.positions[t + 1], ground_z=city.ground_z)
        stop = int(np.flatnonzero(seq.actions == C.ACTION_STOP)[0])
        assert stop == planned.leg_end_frames[-1]
        assert np.linalg.norm(seq.positions[stop] - planned.route.legs[-1].goal) <= 3.1
        for leg, frame in zip(planned.route.legs, planned.leg_end_frames):
            assert (
                np.linalg.norm(seq.positions[frame] - leg.goal) <= 3.1 + 6.0
            )  # a merged block may overshoot
        assert planned.pitch_deg == (-45.0 if planned.category.startswith("high") else 0.0)
        seen_updown |= planned.category.endswith("_updown")
        seen_chain |= len(planned.route.legs) == 2
        if planned.category.endswith("_updown"):
            # take-off and landing each happen only above a free column
            assert seq.actions[0] == C.ACTION_TAKEOFF or seq.actions[-1] == C.ACTION_LANDING
            assert min(seq.positions[0][2], seq.positions[-1][2]) < prepared.pmap.min_flight_z
            assert seq.positions[:, 2].min() >= 1.0
    assert seen_updown and seen_chain


def test_plans_are_deterministic_per_seed(prepared):
    a = plan_trajectory(prepared, np.random.default_rng(3), tiny_config())
    b = plan_trajectory(prepared, np.random.default_rng(3), tiny_config())
    assert a.seq.actions.tolist() == b.seq.actions.tolist() and np.array_equal(
        a.seq.positions, b.seq.positions
    )


def test_units_splits_and_shards_are_deterministic():
    cfg = tiny_config(scenes=SceneConfig(**{**TINY.__dict__, "test_seen_fraction": 0.3}))
    units = scene_units(0, ROLE_TRAIN, cfg)
    assert units == scene_units(0, ROLE_TRAIN, cfg)
    assert {u.split for u in units} <= {C.SPLIT_TRAIN, C.SPLIT_TEST_SEEN}
    assert {u.split for u in scene_units(1, ROLE_UNSEEN, cfg)} == {C.SPLIT_TEST_UNSEEN}
    assert shard_scenes(cfg) == [(0, ROLE_TRAIN), (2, ROLE_TRAIN), (1, ROLE_UNSEEN)]
    shards = [shard_scenes(GenerateConfig(**{**cfg.__dict__, "shard": f"{i}/2"})) for i in range(2)]
    assert shards == [[(0, ROLE_TRAIN), (1, ROLE_UNSEEN)], [(2, ROLE_TRAIN)]]
    unit = WorkUnit(5, 7, C.SPLIT_TRAIN)
    assert unit.seed(0) == WorkUnit(5, 7, C.SPLIT_TEST_SEEN).seed(0) != WorkUnit(5, 8, C.SPLIT_TRAIN).seed(0)
    assert unit.traj_folder(0).count("_") == 2 and WorkUnit(5, 7, "train", KIND_DAGGER).traj_folder(
        0
    ).endswith("_dagger")
    with pytest.raises(ValueError, match="i/N"):
        GenerateConfig(shard="3")
    with pytest.raises(ValueError, match="0 <= i < N"):
        GenerateConfig(shard="2/2")
    with pytest.raises(ValueError, match="unseen_seeds must not be used"):
        SceneConfig(train_seeds=[1, 2], unseen_seeds=[2])


VAL = SceneConfig(**{**TINY.__dict__, "val_seen_per_scene": 2, "val_seeds": [9], "val_unseen_per_scene": 3})


def test_val_units_are_units_of_their_own_that_leave_every_other_unit_as_it_was():
    with_val, without = tiny_config(scenes=VAL), tiny_config()
    train_units = scene_units(0, ROLE_TRAIN, with_val)
    before = scene_units(0, ROLE_TRAIN, without)  # 10 A* units + 0 DAgger units (dagger off)
    assert train_units[: len(before)] == before  # the other splits' units, unchanged and in the same order
    val_units = train_units[len(before) :]
    assert [(u.index, u.split, u.kind) for u in val_units] == [
        (VAL_INDEX_BASE, C.SPLIT_VAL, KIND_ASTAR),
        (VAL_INDEX_BASE + 1, C.SPLIT_VAL, KIND_ASTAR),
    ]
    city = scene_units(9, ROLE_VAL, with_val)  # the validation city: val units only
    assert [(u.index, u.split) for u in city] == [(VAL_INDEX_BASE + i, C.SPLIT_VAL) for i in range(3)]
    assert scene_units(1, ROLE_UNSEEN, with_val) == scene_units(1, ROLE_UNSEEN, without)
    seeds = {u.seed(0) for u in before} | {u.seed(0) for u in scene_units(1, ROLE_UNSEEN, without)}
    assert not seeds & {u.seed(0) for u in val_units + city}  # seeds of their own
    # the validation city comes last: every other scene keeps its shard
    assert shard_scenes(with_val) == [(0, ROLE_TRAIN), (2, ROLE_TRAIN), (1, ROLE_UNSEEN), (9, ROLE_VAL)]
    for shard in ("0/2", "1/2"):
        others = [
            scene for scene in shard_scenes(tiny_config(scenes=VAL, shard=shard)) if scene[1] != ROLE_VAL
        ]
        assert others == shard_scenes(tiny_config(shard=shard))
    with pytest.raises(ValueError, match="val_seeds must not be used"):
        SceneConfig(train_seeds=[1], unseen_seeds=[2], val_seeds=[2], val_unseen_per_scene=1)
    with pytest.raises(ValueError, match="val_unseen_per_scene >= 1"):
        SceneConfig(train_seeds=[1], unseen_seeds=[2], val_seeds=[3])


def test_pending_units_skip_finished_and_rejected_units(tmp_path):
    cfg = tiny_config(output_dir=str(tmp_path))
    ledger = UnitLedger(tmp_path)

    class Writer:  # the dataset writer's answer for episodes on disk
        def has_episode(self, episode_id):
            return episode_id == "embedded-0/astar_data/low_short/kept"

    ledger.append("embedded-0", {"index": 0, "kind": KIND_ASTAR, "status": "rejected", "reason": "no_route"})
    ledger.append(
        "embedded-0",
        {
            "index": 1,
            "kind": KIND_ASTAR,
            "status": "ok",
            "episode_id": "embedded-0/astar_data/low_short/kept",
        },
    )
    ledger.append(
        "embedded-0",
        {
            "index": 2,
            "kind": KIND_ASTAR,
            "status": "ok",
            "episode_id": "embedded-0/astar_data/low_short/lost",
        },
    )
    with ledger.path("embedded-0").open("a") as f:
        f.write('{"index": 3, "kind": "ast')  # torn last line: ignored, unit 3 is done again
    todo = pending_units(cfg, ledger, Writer(), (KIND_ASTAR,))
    assert [u.index for u in todo[0]] == [2, 3, 4, 5, 6, 7, 8, 9]
    assert len(todo[1]) == 10 and len(todo[2]) == 10


def test_summary_counts(tmp_path):
    records = [
        {"status": "ok", "split": "train", "scene_id": "embedded-0", "category": "low_short", "kind": "astar",
         "instruction": "Fly forward to the red tower and stop near it.", "actions": [9, 2, 1, 0],
         "flight_height_m": 12.0, "path_length_m": 15.0},
        {"status": "ok", "split": "test_unseen", "scene_id": "embedded-1", "category": "high_long",
         "kind": "dagger", "instruction": "Turn left, then stop at the blue house.", "actions": [2, 9, 9, 0],
         "flight_height_m": 31.0, "path_length_m": 18.0},
        {"status": "rejected", "reason": "no_route"},
        {"status": "rejected", "reason": "no_route"},
    ]  # fmt: skip
    s = summarize_records(records)
    assert s["trajectories"] == 2 and s["attempts"] == 4 and s["rejected"] == {"no_route": 2}
    assert s["per_split"] == {"test_unseen": 1, "train": 1} and s["dagger_episodes"] == 1
    words = {"fly", "forward", "to", "the", "red", "tower", "and", "stop", "near", "it"}
    words |= {"turn", "left", "then", "at", "blue", "house"}
    assert s["vocabulary_size"] == len(words)
    assert s["instruction_words"]["mean"] == pytest.approx((10 + 8) / 2)
    assert s["action_histogram"] == {"stop": 2, "forward": 1, "turn left": 2, "forward 9": 3}
    assert s["path_length_m"]["mean"] == pytest.approx(16.5)
    assert s["flight_height_m"]["histogram"]["counts"] == [0, 1, 0, 1]


@settings(max_examples=25, deadline=None)
@given(
    cells=st.lists(st.tuples(st.integers(0, 9), st.integers(0, 7), st.integers(0, 5)), max_size=12),
    radius=st.floats(0.0, 3.5),
)
def test_fast_dilation_equals_the_grid_dilation(cells, radius):
    grid = OccupancyGrid.empty(SceneBounds(0, 10, 0, 8, 0, 6), 1.0)
    for c in cells:
        grid.occupied[c] = True
    assert np.array_equal(dilate_grid(grid, radius).occupied, grid.dilate(radius).occupied)


def test_official_env_yaml_becomes_map_and_route_settings(openfly_fixtures):
    scene_cfg = read_scene_config(openfly_fixtures / "env_airsim_16.yaml")
    m = map_config_for(scene_cfg)
    assert (m.voxel_size_m, m.dilate_radius_m, m.bounds) == (1.5, 3, [-1300, 1000, -600, 1000, -200, 200])
    assert (m.elevation_m, m.min_height_thresh_m, m.bev_voxel_size_m, m.pcd_scale_ratio) == (0, 6, 4.0, 1)
    r = route_config_for(scene_cfg.thread_params[0])
    assert (r.min_dist_m, r.max_dist_m, r.height_min_m, r.height_max_m) == (150, 180, 5, 10)
    assert (r.with_turn_prob, r.chain_prob, r.takeoff_landing_prob) == (1.0, 0.0, 1.0)
    ue = route_config_for(read_scene_config(openfly_fixtures / "env_ue_smallcity.yaml").thread_params[0])
    assert (ue.with_turn_prob, ue.min_dist_m, ue.max_dist_m) == (0.0, 60, 100)


def _small_env_yaml(path, name="env_airsim_77", ratio=1.0):
    """An env yaml in the official layout with a 300 m planning volume (the fixtures' are kilometres)."""
    thread = {"name": "t", "nums": 5, "min_dis": 60, "max_dis": 90, "height_min": 5, "height_max": 20,
              "aim_port": 1, "listen_port": 2, "sim_ip": "127.0.0.1", "sim_port": 3, "aimlandmark_nums": 1,
              "add_takeoff_land": False, "with_turn": False}  # fmt: skip
    data = {
        "datagen": {"env": name, "data_type": "low_short", "freq": 2},
        "traj_map": {"DilateRadius": 3, "VoxelWidth": 2, "MapBound": [-150, 150, -150, 150, -10, 100],
                     "LidarDelta": [50, 50, 50], "pcd_scale_ratio": ratio, "traj_scale_ratio": 1,
                     "map_elevation": 0, "min_height_thresh": 6},
        "seg_map": {"bev_voxel_size": 2},
        "thread_params": [thread],
    }  # fmt: skip
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("suffix,binary", [(".pcd", True), (".pcd", False), (".ply", True), (".ply", False)])
def test_real_scene_from_a_point_cloud_file_segmentation_and_landmark_list_round_trip(
    tmp_path, suffix, binary
):
    points = np.concatenate([box_surface_points(lo, hi) for _, lo, hi, *_ in BUILDINGS]) / 2.0  # ratio 2
    pcd = tmp_path / f"env_airsim_77{suffix}"
    write_points(pcd, points, binary=binary)
    yaml_path = _small_env_yaml(tmp_path / "env_airsim_77.yaml", ratio=2.0)
    cfg = generate_config_for_real_scene(yaml_path, segment=True)
    prepared = prepare_scene(real_scene(yaml_path, pcd), cfg)
    assert len(prepared.landmarks) == len(BUILDINGS)
    out = tmp_path / "seg_map_env_airsim_77.jsonl"
    write_landmark_list(out, list(prepared.landmarks.values()), cfg.map.pcd_scale_ratio)
    back = read_landmark_list(out, pcd_scale_ratio=2.0)
    assert np.allclose([lm.position for lm in back], [lm.position for lm in prepared.landmarks.values()])
    assert json.loads(out.read_text().splitlines()[0])["type"] == "building"
    # the list read back drives route sampling + A* like the embedded city's landmark list
    listed = prepare_scene(real_scene(yaml_path, pcd, out), generate_config_for_real_scene(yaml_path))
    planned = plan_trajectory(listed, np.random.default_rng(0), generate_config_for_real_scene(yaml_path))
    assert planned.seq.actions[-1] == C.ACTION_STOP


def test_landmarks_without_height_take_it_from_the_point_cloud(tmp_path):
    points = np.concatenate([box_surface_points(lo, hi) for _, lo, hi, *_ in BUILDINGS])
    pcd = tmp_path / "cloud.ply"
    from openfly_agent.sim.pointcloud import write_ply

    write_ply(pcd, points, binary=False)
    lines = [
        json.dumps({"type": "building", "color": "test", "size": "test", "shape": "test", "feature": "test",
                    "filename": f"X={(lo[0] + hi[0]) / 2}Y={(lo[1] + hi[1]) / 2}Z=0.png"})
        for _, lo, hi, *_ in BUILDINGS
    ]  # fmt: skip
    listing = tmp_path / "seg_map_env_airsim_77.jsonl"
    listing.write_text("\n".join(lines) + "\n")
    yaml_path = _small_env_yaml(tmp_path / "env_airsim_77.yaml")
    prepared = prepare_scene(real_scene(yaml_path, pcd, listing), generate_config_for_real_scene(yaml_path))
    tops = sorted(lm.position[2] for lm in prepared.landmarks.values())
    assert tops == pytest.approx(sorted(hi[2] for _, _, hi, *_ in BUILDINGS))


def test_ledger_appends_after_a_torn_line_stay_readable(tmp_path):
    ledger = UnitLedger(tmp_path)
    ledger.append("s", {"index": 0})
    with ledger.path("s").open("a") as f:
        f.write('{"index": 1, "ki')  # the process died here
    ledger.append("s", {"index": 2})
    ledger.append("s", {"index": 3})
    assert [r["index"] for r in ledger.read("s")] == [0, 2, 3]
    assert ledger.path("s").read_text().count("\n") == 4


def test_chained_routes_visit_three_or_four_landmarks_in_order_and_the_instruction_names_them(prepared):
    from openfly_agent.toolchain.instructions import template_instruction
    from openfly_agent.toolchain.pipeline import instruction_request
    from openfly_agent.toolchain.render import RenderedFrames

    cfg = tiny_config()
    cfg.route.chain_prob, cfg.route.chain_landmarks = 1.0, [3, 4]
    cfg.instructions.name_every_target = True
    sampler = RouteSampler(prepared.pmap, list(prepared.landmarks.values()), cfg.route)
    chained = dataclasses.replace(prepared, sampler=sampler)
    counts = set()
    for seed in range(12):
        try:
            planned = plan_trajectory(chained, np.random.default_rng(seed), cfg)
        except Rejected:
            continue
        route, seq = planned.route, planned.seq
        ids = route.landmark_ids
        counts.add(len(ids))
        assert len(ids) in (3, 4) and len(set(ids)) == len(ids) == len(planned.leg_end_frames)
        assert planned.leg_end_frames == sorted(planned.leg_end_frames)
        origin = route.start.position
        for k, (leg, frame) in enumerate(zip(route.legs, planned.leg_end_frames)):
            assert (
                np.linalg.norm(seq.positions[frame] - leg.goal) <= 3.1 + 6.0
            )  # a merged block may overshoot
            if k:  # each next landmark lies 40-90 m from the previous goal, at a bearing 30-150 deg off
                previous = route.legs[k - 1].goal
                centre = np.array(leg.landmark.position[:2])
                assert 40 <= np.linalg.norm(centre - previous[:2]) <= 90
                heading = np.arctan2(*(previous[1::-1] - origin[1::-1]))
                bearing = np.arctan2(*(centre[::-1] - previous[1::-1]))
                assert 30 <= abs(np.degrees((bearing - heading + np.pi) % (2 * np.pi) - np.pi)) <= 150
                origin = previous
        # no boxes: the instruction names the route's targets only, each by colour and type, in order
        rendered = RenderedFrames([], [{} for _ in range(len(seq))])
        text = template_instruction(instruction_request(chained, planned, rendered, seed, cfg))
        at = 0
        for landmark_id in ids:
            landmark = prepared.landmarks[landmark_id]
            at = text.index(f"{landmark.color} {landmark.type}", at) + 1
    assert counts == {3, 4}


def test_leg_boxes_hold_the_target_of_each_frames_leg():
    """Three legs ending at frames 1, 3 and 5: frame 0 is leg 0's, a leg's end frame the next leg's first
    decision (frames 1-2: leg 1, 3-5: leg 2); a target out of the frame gives a zero box, marked invisible."""
    a, b, c = (0.1, 0.1, 0.2, 0.2), (0.4, 0.4, 0.1, 0.1), (0.7, 0.5, 0.3, 0.3)
    frames = [{"a": a, "c": c}, {"a": a, "b": b}, {"c": c}, {"b": b, "c": c}, {}, {"c": c}]
    rendered = RenderedFrames([], frames)
    ends = [1, 3, 5]
    assert [leg_of_frame(ends, t) for t in range(6)] == [0, 1, 1, 2, 2, 2]
    boxes, visible = leg_target_boxes(rendered, ["a", "b", "c"], ends)
    assert visible.tolist() == [True, True, False, True, False, True]
    np.testing.assert_array_equal(boxes, [a, b, (0, 0, 0, 0), c, (0, 0, 0, 0), c])
    final_boxes, final_visible = target_boxes(
        rendered, "c"
    )  # the released labels: the last target throughout
    assert final_visible.tolist() == [True, False, True, True, False, True]
    np.testing.assert_array_equal(final_boxes, [c, (0, 0, 0, 0), c, c, (0, 0, 0, 0), c])
    with pytest.raises(ValueError, match="3 targets for 2 legs"):
        leg_target_boxes(rendered, ["a", "b", "c"], [3, 5])


def test_render_box_target_picks_the_boxes_a_chained_episode_stores(prepared):
    """`render.box_target=leg`: each frame of a chained route's episode holds its leg's target; `final` (the
    default) the last target's, as before; another value is refused."""
    cfg = tiny_config()
    cfg.route.chain_prob, cfg.route.chain_landmarks = 1.0, [3, 3]
    sampler = RouteSampler(prepared.pmap, list(prepared.landmarks.values()), cfg.route)
    chained = dataclasses.replace(prepared, sampler=sampler)
    planned = next(p for p in (_planned_or_none(chained, seed, cfg) for seed in range(12)) if p is not None)
    ids = planned.route.landmark_ids
    box = {landmark_id: (0.1 * (k + 1), 0.5, 0.1, 0.1) for k, landmark_id in enumerate(ids)}
    rendered = RenderedFrames([], [dict(box) for _ in range(len(planned.seq))])  # every target in every frame
    unit = WorkUnit(0, 0, C.SPLIT_TRAIN)
    leg = build_episode(unit, 0, "s", planned, rendered, box_target="leg")
    final = build_episode(unit, 0, "s", planned, rendered)
    expected = [box[ids[leg_of_frame(planned.leg_end_frames, t)]] for t in range(len(planned.seq))]
    np.testing.assert_array_equal(leg.boxes, expected)
    assert {tuple(b) for b in leg.boxes} == set(box.values())  # each of the three legs holds frames
    np.testing.assert_array_equal(final.boxes, [box[ids[-1]]] * len(planned.seq))
    for episode in (leg, final):  # each leg's goal, the last the episode's goal, whatever the boxes
        np.testing.assert_array_equal(episode.leg_goals, [lg.goal for lg in planned.route.legs])
        np.testing.assert_array_equal(episode.leg_goals[-1], episode.goal)
    with pytest.raises(ValueError, match="render.box_target must be one of"):
        RenderConfig(box_target="next")


def _planned_or_none(prepared, seed, cfg):
    try:
        return plan_trajectory(prepared, np.random.default_rng(seed), cfg)
    except Rejected:
        return None

"""Official landmark lists and env yaml configs read into our scene types (real fixture files)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from openfly_agent.sim.real_scene import (
    GS_SCALE_RATIOS,
    default_pcd_scale_ratio,
    engine_of,
    read_landmark_list,
    read_scene_config,
)
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.utils.errors import RecordError

SCENES = ("env_airsim_16", "env_gs_nwpu02", "env_ue_smallcity")


def test_engine_and_scale_from_scene_name():
    assert [engine_of(s) for s in SCENES] == ["airsim", "gs", "ue"]
    assert default_pcd_scale_ratio("env_airsim_23") == 1.0
    assert default_pcd_scale_ratio("env_gs_sjtu02") == 4.75
    assert GS_SCALE_RATIOS == {
        "env_gs_ecust": 5.6,
        "env_gs_nwpu01": 6.65,
        "env_gs_nwpu02": 5.15,
        "env_gs_sjtu01": 5.42,
        "env_gs_sjtu02": 4.75,
    }
    with pytest.raises(ValueError, match="env_ue_"):
        engine_of("env_gtav")
    with pytest.raises(ValueError, match="pass it explicitly"):
        default_pcd_scale_ratio("env_gs_unknown")


def test_landmark_lists_convert_units_per_engine(openfly_fixtures):
    airsim = read_landmark_list(openfly_fixtures / "seg_map_env_airsim_16.jsonl")
    gs = read_landmark_list(openfly_fixtures / "seg_map_env_gs_nwpu02.jsonl")
    ue = read_landmark_list(openfly_fixtures / "seg_map_env_ue_smallcity.jsonl")
    assert (len(airsim), len(gs), len(ue)) == (327, 88, 610)
    # AirSim: metres as written ("X=-122.22000000000003Y=-866.76Z=33.82895278930664.png")
    assert airsim[0].position == pytest.approx((-122.22, -866.76, 33.82895278930664))
    # 3DGS: multiplied by nwpu02's pcd_scale_ratio 5.15 ("X=-50.33761978149414Y=8.783727645874023Z=0.png")
    assert gs[0].position == pytest.approx((-50.33761978149414 * 5.15, 8.783727645874023 * 5.15, 0.0))
    # UE: centimetres, left-handed -> /100 and y negated ("X=-7986.052Y=-56308.875Z=0.png")
    assert ue[0].position == pytest.approx((-79.86052, 563.08875, 0.0))
    assert ue[0].color == "grey" and ue[0].size == "mid-rise" and ue[0].shape == "rectangular"
    assert ue[0].description() == "grey building with a grid-like window pattern"
    assert airsim[0].description() == "building"  # placeholder "test" attributes
    assert ue[0].landmark_id == "env_ue_smallcity/0" and ue[0].attributes["line"] == 1
    assert len({lm.landmark_id for lm in ue}) == len(ue)


def test_landmarks_fall_inside_the_scene_bounds(openfly_fixtures):
    for scene in ("env_gs_nwpu02", "env_ue_smallcity"):
        config = read_scene_config(openfly_fixtures / f"{scene}.yaml")
        landmarks = read_landmark_list(openfly_fixtures / f"seg_map_{scene}.jsonl")
        xy = np.array([lm.position for lm in landmarks])
        xy[:, 2] = 0.0
        flat = SceneBounds(*config.map_bound.as_list()[:4], -1.0, 1.0)
        assert flat.contains(xy).all(), scene


def test_explicit_ratio_and_env_override(openfly_fixtures):
    raw = read_landmark_list(openfly_fixtures / "seg_map_env_gs_nwpu02.jsonl", pcd_scale_ratio=1.0)
    assert raw[0].position == pytest.approx((-50.33761978149414, 8.783727645874023, 0.0))
    renamed = read_landmark_list(openfly_fixtures / "seg_map_env_gs_nwpu02.jsonl", env="env_gs_sjtu02")
    assert renamed[0].position[0] == pytest.approx(-50.33761978149414 * 4.75)
    assert renamed[0].landmark_id == "env_gs_sjtu02/0"


def test_scene_configs_hold_every_field(openfly_fixtures):
    airsim = read_scene_config(openfly_fixtures / "env_airsim_16.yaml")
    assert (airsim.env, airsim.engine, airsim.data_type, airsim.freq) == (
        "env_airsim_16",
        "airsim",
        "low_long",
        2.0,
    )
    assert (airsim.dilate_radius, airsim.voxel_width) == (3.0, 1.5)
    assert airsim.map_bound == SceneBounds(-1300, 1000, -600, 1000, -200, 200)
    assert airsim.lidar_delta == (200.0, 200.0, 50.0)
    assert (airsim.pcd_scale_ratio, airsim.traj_scale_ratio, airsim.map_elevation) == (1.0, 1.0, 0.0)
    assert (airsim.min_height_thresh, airsim.bev_voxel_size) == (6.0, 4.0)
    (thread,) = airsim.thread_params
    assert (thread.name, thread.nums, thread.min_dis, thread.max_dis) == ("thread_1", 1000, 150.0, 180.0)
    assert (thread.height_min, thread.height_max, thread.aim_port, thread.listen_port) == (
        5.0,
        10.0,
        9999,
        9998,
    )
    assert (thread.sim_ip, thread.sim_port, thread.aimlandmark_nums) == ("127.0.0.1", 9000, 1)
    assert thread.add_takeoff_land and thread.with_turn and thread.extra == {}

    gs = read_scene_config(openfly_fixtures / "env_gs_nwpu02.yaml")
    assert (gs.pcd_scale_ratio, gs.map_elevation, gs.bev_voxel_size) == (5.15, -50.0, 5.0)
    assert gs.planning_bounds == SceneBounds(-1000, 2000, -1000, 1000, -50, 100)
    assert not gs.thread_params[0].add_takeoff_land and gs.thread_params[0].height_min == 60.0

    ue = read_scene_config(openfly_fixtures / "env_ue_smallcity.yaml")
    assert (ue.freq, ue.pcd_scale_ratio, ue.traj_scale_ratio, ue.bev_voxel_size) == (0.5, 100.0, 100.0, 3.0)


def _write_variant(tmp_path, openfly_fixtures, scene: str, old: str, new: str):
    text = (openfly_fixtures / f"{scene}.yaml").read_text()
    assert old in text
    path = tmp_path / f"{scene}.yaml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize(
    ("old", "new", "line", "field", "problem"),
    [
        (
            "[-1000, 2000, -1000, 1000, -100, 100]",
            "[-1000, 2000, -1000, 1000, -100]",
            9,
            "traj_map.MapBound",
            "xmin",
        ),
        ("nums: 4000", "nums: many", 21, "thread_params[0].nums", "integer"),
        ("    with_turn: false", "", 20, "thread_params[0].with_turn", "missing"),
        ('env:                        "env_gs_nwpu02"', 'env: "env_gs_other"', 2, "datagen.env", "file name"),
        ("VoxelWidth:                 1.5", "VoxelWidth: 0", 8, "traj_map.VoxelWidth", "positive"),
    ],
)
def test_bad_scene_config_names_file_line_and_field(
    tmp_path, openfly_fixtures, old, new, line, field, problem
):
    path = _write_variant(tmp_path, openfly_fixtures, "env_gs_nwpu02", old, new)
    with pytest.raises(RecordError, match=problem) as info:
        read_scene_config(path)
    err = info.value
    assert (err.file, err.field_name) == (str(path), field)
    assert err.line == line  # a missing key points at its parent entry
    assert str(err).startswith(f"{path}:")


def _record(**changes) -> str:
    record = {
        "type": "b",
        "color": "c",
        "size": "s",
        "shape": "s",
        "feature": "f",
        "filename": "X=1Y=2Z=3.png",
    }
    record.update(changes)
    return json.dumps({k: v for k, v in record.items() if v is not None})


@pytest.mark.parametrize(
    ("line_text", "field", "problem"),
    [
        ('{"type": "building", "color": "grey"', "<json>", "not valid JSON"),
        (_record(filename=None), "filename", "missing"),
        (_record(color=3), "color", "string"),
        (_record(filename="X=1Y=2.png"), "filename", "X=<x>Y=<y>Z=<z>.png"),
    ],
)
def test_bad_landmark_record_names_file_line_and_field(tmp_path, line_text, field, problem):
    path = tmp_path / "seg_map_env_ue_test.jsonl"
    good = _record(filename="X=1e2Y=-2Z=.5.png")
    path.write_text(good + "\n\n" + line_text + "\n")
    with pytest.raises(RecordError, match=problem) as info:
        read_landmark_list(path)
    assert (info.value.line, info.value.field_name) == (3, field)
    path.write_text(good + "\n")
    assert read_landmark_list(path)[0].position == pytest.approx((1.0, 0.02, 0.005))  # cm, y negated

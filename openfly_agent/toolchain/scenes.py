"""Scene sources for the toolchain: the embedded city of a seed, or a real scene's point cloud + lists.

A `ToolchainScene` is what the paper's pipeline starts from: a point cloud, named landmarks (a list, or
none to segment them), bounds and ground height. Real scenes take every map / route parameter from their
official `env_*.yaml` (`map_config_for`, `route_config_for`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openfly_agent.sim.city import CityConfig, generate_city, scene_id_of
from openfly_agent.sim.pointcloud import read_points
from openfly_agent.sim.real_scene import RealSceneConfig, ThreadParams, read_landmark_list, read_scene_config
from openfly_agent.sim.scene import Landmark, SceneBounds
from openfly_agent.toolchain.config import (
    GenerateConfig,
    MapConfig,
    RouteConfig,
    SceneConfig,
    SegmentationConfig,
)


@dataclass
class ToolchainScene:
    """Inputs of the toolchain for one scene."""

    scene_id: str
    points: np.ndarray  # (N, 3) in point cloud units (MapConfig.pcd_scale_ratio converts to metres)
    landmarks: list[Landmark]  # named landmarks in metres; empty = segment them from the points
    bounds: SceneBounds  # metres
    ground_z: float  # metres
    tree_height_m: float = 0.0  # tallest non-landmark obstacle (trees) above the ground, metres


def city_config_for(cfg: SceneConfig) -> CityConfig:
    """The embedded city parameters of a scene config (the simulator must build the same city)."""
    city = CityConfig(size_m=cfg.city_size_m)
    if cfg.city_buildings is not None:
        city = dataclasses.replace(city, n_buildings=cfg.city_buildings)
    return city


def embedded_scene(seed: int, cfg: SceneConfig) -> ToolchainScene:
    """The embedded city of `seed` as a point cloud with its landmark list (attributes from the generator)."""
    city = generate_city(seed, city_config_for(cfg))
    trees = max((tree.height_m for tree in city.trees), default=0.0)
    return ToolchainScene(
        scene_id=scene_id_of(seed),
        points=city.point_cloud(cfg.point_spacing_m),
        landmarks=city.landmarks,
        bounds=city.bounds,
        ground_z=float(city.ground_z),
        tree_height_m=float(trees),
    )


def real_scene(
    env_yaml: str | Path, point_cloud: str | Path, landmark_list: str | Path | None = None
) -> ToolchainScene:
    """A real scene from its official files: env yaml, point cloud (.pcd / .ply) and landmark list (.jsonl).

    Without a landmark list the landmarks are segmented from the point cloud (SegmentationConfig).
    """
    scene_cfg = read_scene_config(env_yaml)
    landmarks = []
    if landmark_list is not None:
        landmarks = read_landmark_list(
            landmark_list, env=scene_cfg.env, pcd_scale_ratio=scene_cfg.pcd_scale_ratio
        )
    return ToolchainScene(
        scene_id=scene_cfg.env,
        points=read_points(point_cloud),
        landmarks=landmarks,
        bounds=scene_cfg.planning_bounds,
        ground_z=scene_cfg.map_elevation,
    )


def map_config_for(scene_cfg: RealSceneConfig) -> MapConfig:
    """`traj_map` + `seg_map` of an official env yaml as a MapConfig."""
    return MapConfig(
        voxel_size_m=scene_cfg.voxel_width,
        dilate_radius_m=scene_cfg.dilate_radius,
        bounds=scene_cfg.map_bound.as_list(),
        elevation_m=scene_cfg.map_elevation,
        min_height_thresh_m=scene_cfg.min_height_thresh,
        bev_voxel_size_m=scene_cfg.bev_voxel_size,
        pcd_scale_ratio=scene_cfg.pcd_scale_ratio,
    )


def route_config_for(thread: ThreadParams, base: RouteConfig | None = None) -> RouteConfig:
    """One `thread_params` entry as a RouteConfig (turn / chain / take-off flags: probability 0 or 1)."""
    return dataclasses.replace(
        base or RouteConfig(),
        height_min_m=thread.height_min,
        height_max_m=thread.height_max,
        min_dist_m=thread.min_dis,
        max_dist_m=thread.max_dis,
        with_turn_prob=1.0 if thread.with_turn else 0.0,
        chain_prob=1.0 if thread.aimlandmark_nums >= 2 else 0.0,
        takeoff_landing_prob=1.0 if thread.add_takeoff_land else 0.0,
    )


def generate_config_for_real_scene(
    env_yaml: str | Path, segment: bool = False, thread: int = 0
) -> GenerateConfig:
    """A GenerateConfig whose map / route / segmentation settings come from an official env yaml."""
    scene_cfg = read_scene_config(env_yaml)
    if not scene_cfg.thread_params:
        raise ValueError(f"{env_yaml}: no thread_params entry to take the route settings from")
    return GenerateConfig(
        map=map_config_for(scene_cfg),
        route=route_config_for(scene_cfg.thread_params[thread]),
        segmentation=SegmentationConfig(source="segment" if segment else "scene"),
    )

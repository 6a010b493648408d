"""One trajectory from a prepared scene: route -> A* -> codebook actions -> filters -> frames -> episode.

A work unit (scene seed, trajectory index) gets its own seed, so the result does not depend on which worker
runs it or in which order. Rejections raise `Rejected` with the reason the summary counts.
"""

from __future__ import annotations

import datetime as dt
import time
from dataclasses import dataclass, field, replace

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.sim import dynamics
from openfly_agent.sim.base import Simulator
from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain import filters
from openfly_agent.toolchain.actions import (
    ActionSequence,
    build_action_sequence,
    camera_pitch_for,
    sequence_category,
)
from openfly_agent.toolchain.astar import ActionSpaceAStar, PlanningFailed
from openfly_agent.toolchain.config import BOX_TARGET_FINAL, BOX_TARGET_LEG, GenerateConfig
from openfly_agent.toolchain.instructions import InstructionRequest
from openfly_agent.toolchain.landmarks import fill_landmark_heights, segment_landmarks
from openfly_agent.toolchain.render import RenderedFrames, leg_target_boxes, render_poses, target_boxes
from openfly_agent.toolchain.routes import Route, RouteSampler, RouteSamplingFailed
from openfly_agent.toolchain.scenes import ToolchainScene
from openfly_agent.toolchain.visibility import route_visibility
from openfly_agent.toolchain.voxel_map import PlanningMap, build_planning_map
from openfly_agent.utils.geometry import Pose, path_length

KIND_ASTAR = "astar"  # an A* trajectory
KIND_DAGGER = "dagger"  # a recovery episode of the noisy expert
KIND_DAGGER_POLICY = "dagger_policy"  # a recovery episode of a trained policy (`dagger` command)
DAGGER_KINDS = (KIND_DAGGER, KIND_DAGGER_POLICY)
_KIND_CODE = {KIND_ASTAR: 0, KIND_DAGGER: 1, KIND_DAGGER_POLICY: 2}
_EPOCH = dt.datetime(2026, 1, 1)
_TAKEOFF_CLEARANCE_M = 1.0  # take-off starts / landing ends this far above the ground (at least)


class Rejected(Exception):
    """A work unit that produced no episode; `reason` is counted in the summary."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        super().__init__(f"{reason}{': ' + detail if detail else ''}")


@dataclass(frozen=True)
class WorkUnit:
    """One trajectory to generate: scene seed, index within the scene, split, kind (A* or DAgger)."""

    scene_seed: int
    index: int
    split: str
    kind: str = KIND_ASTAR

    def seed(self, base_seed: int) -> int:
        """Deterministic per-unit seed (independent of workers and order)."""
        key = [int(base_seed), int(self.scene_seed), int(self.index), _KIND_CODE[self.kind]]
        return int(np.random.SeedSequence(key).generate_state(1)[0])

    def stamp(self) -> dt.datetime:
        return _EPOCH + dt.timedelta(days=self.scene_seed % 3650, seconds=self.index)

    def traj_folder(self, base_seed: int) -> str:
        """Release-style folder name `Y-M-D_h-m-s_<number>` (+ `_dagger` for recovery episodes)."""
        s = self.stamp()
        name = f"{s.year}-{s.month}-{s.day}_{s.hour}-{s.minute}-{s.second}_{self.seed(base_seed) % 10**9}"
        return name + ("_dagger" if self.kind in DAGGER_KINDS else "")


@dataclass
class PreparedScene:
    """A scene with its planning map, landmarks, route sampler and planner (built once per worker)."""

    scene: ToolchainScene
    pmap: PlanningMap
    landmarks: dict[str, Landmark]
    sampler: RouteSampler
    astar: ActionSpaceAStar
    tree_height_m: float


def prepare_scene(scene: ToolchainScene, cfg: GenerateConfig) -> PreparedScene:
    """Voxel / BEV maps from the point cloud, landmarks (given or segmented), sampler and planner."""
    pmap = build_planning_map(scene.points, cfg.map, scene.bounds, scene.ground_z)
    if cfg.segmentation.source == "segment" or not scene.landmarks:
        points_m = scene.points * cfg.map.pcd_scale_ratio
        landmarks = segment_landmarks(
            points_m, pmap.bounds, pmap.min_flight_z, cfg.map.bev_voxel_size_m, cfg.segmentation
        )
    else:
        landmarks = fill_landmark_heights(scene.landmarks, pmap, cfg.segmentation.height_window_m)
    tree = cfg.filters.tree_height_m if cfg.filters.tree_height_m is not None else scene.tree_height_m
    return PreparedScene(
        scene=scene,
        pmap=pmap,
        landmarks={lm.landmark_id: lm for lm in landmarks},
        sampler=RouteSampler(pmap, landmarks, cfg.route),
        astar=ActionSpaceAStar(pmap, cfg.planner),
        tree_height_m=float(tree),
    )


@dataclass
class PlannedTrajectory:
    route: Route
    seq: ActionSequence
    leg_end_frames: list[int]  # frame where each leg ends; the last is the STOP frame
    category: str
    pitch_deg: float
    expansions: int


def _vertical_steps(prepared: PreparedScene, xy: np.ndarray, z_top: float) -> int:
    """3 m steps between z_top and the ground at xy if that column is free, else 0 (no take-off / landing)."""
    pmap = prepared.pmap
    steps = int(np.floor((z_top - pmap.elevation - _TAKEOFF_CLEARANCE_M) / C.STEP_METERS))
    if steps <= 0:
        return 0
    zs = np.arange(z_top, z_top - steps * C.STEP_METERS - 1e-9, -0.5 * pmap.voxel_size)
    column = np.column_stack([np.repeat(xy[None], len(zs), axis=0), zs])
    return 0 if pmap.dilated.is_occupied(column).any() else steps


def plan_trajectory(
    prepared: PreparedScene, rng: np.random.Generator, cfg: GenerateConfig, allow_updown: bool = True
) -> PlannedTrajectory:
    """Sample a route and plan it (take-off / landing only if `allow_updown` and the route asks for it).

    Raises:
        Rejected: no_route, astar_<reason>, too_few_actions / too_many_actions, below_tree_height.
    """
    try:
        route = prepared.sampler.sample(rng)
    except RouteSamplingFailed as err:
        raise Rejected("no_route", str(err)) from None
    pose, primitives, leg_ends, expansions = route.start, [], [], 0
    for leg in route.legs:
        try:
            result = prepared.astar.plan(pose, leg.goal)
        except PlanningFailed as err:
            raise Rejected(f"astar_{err.reason}", str(err)) from None
        primitives += result.primitives
        leg_ends.append(len(primitives))
        expansions += result.expansions
        pose = dynamics.rollout(pose, result.primitives)[-1]
    takeoff = landing = 0
    if route.takeoff_landing and allow_updown:
        takeoff = _vertical_steps(prepared, route.start.position[:2], route.start.z)
        landing = _vertical_steps(prepared, pose.position[:2], pose.z)
    start = Pose(route.start.x, route.start.y, route.start.z - takeoff * C.STEP_METERS, route.start.yaw)
    seq = build_action_sequence(start, primitives, takeoff, landing)
    # a leg ends at the first kept frame whose raw primitive index reaches the leg's last primitive
    leg_end_frames = [int(np.searchsorted(seq.raw_index, takeoff + end)) for end in leg_ends]
    for reason in (
        filters.check_action_count(seq.actions, cfg.filters),
        filters.check_height(seq.positions, seq.actions, prepared.pmap.elevation, prepared.tree_height_m),
    ):
        if reason:
            raise Rejected(reason)
    category = sequence_category(seq, prepared.pmap.elevation, cfg.categories)
    return PlannedTrajectory(route, seq, leg_end_frames, category, camera_pitch_for(category), expansions)


@dataclass
class UnitResult:
    """What a worker sends back: an episode (instruction still empty) with frames, or a rejection."""

    unit: WorkUnit
    reason: str | None = None  # None = success
    episode: Episode | None = None
    frames: list[np.ndarray] | None = None
    request: InstructionRequest | None = None
    stats: dict = field(default_factory=dict)


def route_episode(
    episode_id: str, scene_id: str, planned: PlannedTrajectory, split: str | None = None
) -> Episode:
    """The planned trajectory as an episode without frames (frame ids 0..T-1, no boxes, instruction empty): its
    start pose, actions, final goal and each leg's goal, target landmarks and camera pitch, what a closed-loop
    rollout starts from."""
    seq = planned.seq
    return Episode(
        episode_id=episode_id,
        scene_id=scene_id,
        instruction="",
        actions=seq.actions,
        positions=seq.positions,
        yaws=seq.yaws,
        frame_ids=[str(t) for t in range(len(seq))],
        split=split,
        category=planned.category,
        pitch_deg=planned.pitch_deg,
        landmark_ids=list(planned.route.landmark_ids),
        goal=np.asarray(planned.route.legs[-1].goal, dtype=np.float64),
        leg_goals=np.array([leg.goal for leg in planned.route.legs], dtype=np.float64),
    )


def build_episode(
    unit: WorkUnit,
    base_seed: int,
    scene_id: str,
    planned: PlannedTrajectory,
    rendered: RenderedFrames,
    box_target: str = BOX_TARGET_FINAL,
) -> Episode:
    """The OpenFly-format episode of a planned, rendered trajectory (instruction filled in later); its boxes are
    those of `box_target` (`render.box_target`)."""
    stamp = unit.stamp().strftime("%Y%m%d_%H%M%S")
    if box_target == BOX_TARGET_LEG:
        boxes, visible = leg_target_boxes(rendered, planned.route.landmark_ids, planned.leg_end_frames)
    else:
        boxes, visible = target_boxes(rendered, planned.route.landmark_ids[-1])
    episode_id = f"{scene_id}/astar_data/{planned.category}/{unit.traj_folder(base_seed)}"
    return replace(
        route_episode(episode_id, scene_id, planned, unit.split),
        frame_ids=[f"{stamp}_{k}" for k in planned.seq.raw_index],
        boxes=boxes,
        box_visible=visible,
    )


def instruction_request(
    prepared: PreparedScene,
    planned: PlannedTrajectory,
    rendered: RenderedFrames,
    seed: int,
    cfg: GenerateConfig,
) -> InstructionRequest:
    """What the instruction backend needs; frames only travel for the VLM backend."""
    used = set(planned.route.landmark_ids).union(*[set(b) for b in rendered.boxes])
    return InstructionRequest(
        actions=planned.seq.actions,
        frame_boxes=rendered.boxes,
        landmarks={i: prepared.landmarks[i] for i in used if i in prepared.landmarks},
        target_ids=list(planned.route.landmark_ids),
        leg_end_frames=planned.leg_end_frames,
        seed=seed,
        frames=rendered.frames if cfg.instructions.backend == "vlm" else None,
        min_box_area=cfg.instructions.min_box_area,
        merge_short_m=cfg.instructions.merge_short_m,
        name_every_target=cfg.instructions.name_every_target,
        name_passed_landmark=cfg.instructions.name_passed_landmark,
    )


def generate_unit(prepared: PreparedScene, sim: Simulator, unit: WorkUnit, cfg: GenerateConfig) -> UnitResult:
    """Plan, filter, render and package one A* trajectory."""
    seed = unit.seed(cfg.seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    try:
        planned = plan_trajectory(prepared, rng, cfg)
    except Rejected as err:
        return UnitResult(unit, reason=err.reason, stats={"plan_s": time.perf_counter() - t0})
    t1 = time.perf_counter()
    rendered = render_poses(
        sim,
        prepared.scene.scene_id,
        planned.seq.poses,
        planned.pitch_deg,
        planned.seq.actions,
        cfg.render.min_box_pixels,
    )
    t2 = time.perf_counter()
    stats = {"plan_s": t1 - t0, "render_s": t2 - t1, "expansions": planned.expansions}
    reason = filters.check_frames(rendered.frames, cfg.filters)
    if reason:
        return UnitResult(unit, reason=reason, stats=stats)
    episode = build_episode(unit, cfg.seed, prepared.scene.scene_id, planned, rendered, cfg.render.box_target)
    request = instruction_request(prepared, planned, rendered, seed, cfg)
    nav = planned.seq.positions[planned.seq.actions >= 0]
    stats.update(
        flight_height_m=float(planned.route.flight_z - prepared.pmap.elevation),
        path_length_m=float(path_length(nav)),
        num_frames=len(episode),
        landmarks=len(planned.route.landmark_ids),
        **route_visibility(request),
    )
    return UnitResult(unit, episode=episode, frames=rendered.frames, request=request, stats=stats)

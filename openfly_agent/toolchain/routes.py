"""Route sampling around landmarks (official `traj_gen`, docs/OFFICIAL_OPENFLY.md 7.4).

Flight height ~ U(floor + h, floor + H); a landmark whose top reaches that height (minus a slack); a start
on the ring [r, R] around it, outside every footprint and obstacle; the goal found by walking from the
landmark towards the start in 1 m steps until outside its (dilated) footprint; optionally a route that must
turn (straight line blocked), and a chained route: more legs, each to a landmark not visited yet that lies
[min_dist, max_dist] from the previous goal at a bearing 30-150 deg off the previous leg's heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.config import RouteConfig
from openfly_agent.toolchain.landmarks import landmark_top, landmark_xy
from openfly_agent.toolchain.voxel_map import PlanningMap
from openfly_agent.utils.geometry import Pose, wrap_yaw


class RouteSamplingFailed(RuntimeError):
    """No valid start / goal found within the configured number of tries."""

    reason = "no_route"


@dataclass
class RouteLeg:
    landmark: Landmark
    goal: np.ndarray  # (3,) metres, outside the landmark's dilated footprint, at flight height


@dataclass
class Route:
    """What A* is asked to connect: start pose, then one goal per landmark leg."""

    start: Pose
    legs: list[RouteLeg]
    flight_z: float
    takeoff_landing: bool = False
    with_turn: bool = False
    landmark_ids: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.landmark_ids = [leg.landmark.landmark_id for leg in self.legs]


def _walk_out_of_footprint(
    pmap: PlanningMap, origin_xy: np.ndarray, towards_xy: np.ndarray, z: float
) -> np.ndarray | None:
    """First point on origin -> towards (1 m steps) that is off the dilated BEV footprint and free in 3-D."""
    span = float(np.linalg.norm(towards_xy - origin_xy))
    if span < 1.0:
        return None
    t = np.arange(0.0, span, 1.0)[:, None] / span
    xy = origin_xy + t * (towards_xy - origin_xy)  # (S, 2)
    pts = np.concatenate([xy, np.full((len(xy), 1), z)], axis=1)
    ok = ~pmap.bev_blocked(xy) & pmap.is_free(pts)
    if not ok.any():
        return None
    return pts[int(np.argmax(ok))]


def _straight_line_free(pmap: PlanningMap, a: np.ndarray, b: np.ndarray) -> bool:
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / (0.5 * pmap.voxel_size))) + 1)
    samples = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    return bool(pmap.is_free(samples).all())


class RouteSampler:
    """Samples `Route`s on one scene. Deterministic given the numpy Generator passed to `sample`."""

    def __init__(self, pmap: PlanningMap, landmarks: list[Landmark], cfg: RouteConfig | None = None):
        self.pmap, self.cfg = pmap, cfg or RouteConfig()
        bounds = pmap.bounds
        self.landmarks = [
            lm
            for lm in landmarks
            if bounds.xmin <= lm.position[0] <= bounds.xmax and bounds.ymin <= lm.position[1] <= bounds.ymax
        ]
        if not self.landmarks:
            raise ValueError("RouteSampler: no landmark lies inside the planning map bounds")
        self._tops = np.array([landmark_top(lm) for lm in self.landmarks])
        self._xy = np.array([landmark_xy(lm) for lm in self.landmarks])

    def sample(self, rng: np.random.Generator) -> Route:
        """One route; raises RouteSamplingFailed when the tries run out."""
        cfg = self.cfg
        flight_z = self.pmap.min_flight_z + rng.uniform(cfg.height_min_m, cfg.height_max_m)
        with_turn = rng.random() < cfg.with_turn_prob
        chain = rng.random() < cfg.chain_prob
        takeoff_landing = rng.random() < cfg.takeoff_landing_prob
        lo, hi = cfg.chain_landmarks
        # drawn only for a range, so [2, 2] keeps the draws (and the routes) of the 2-landmark chains
        n_landmarks = (int(rng.integers(lo, hi + 1)) if hi > lo else lo) if chain else 1
        candidates = np.flatnonzero(self._tops > flight_z - cfg.landmark_top_slack_m)
        if len(candidates) == 0:
            raise RouteSamplingFailed(f"no landmark reaches {flight_z - cfg.landmark_top_slack_m:.1f} m")
        for index in rng.permutation(candidates)[: cfg.max_landmark_tries]:
            first = self._first_leg(self.landmarks[index], flight_z, with_turn, rng)
            if first is None:
                continue
            start_xyz, leg = first
            legs = self._chain(start_xyz, leg, n_landmarks, flight_z, rng)
            if legs is None:
                continue
            bearing = math.atan2(leg.goal[1] - start_xyz[1], leg.goal[0] - start_xyz[0])
            yaw = wrap_yaw(
                bearing + math.radians(rng.uniform(-cfg.start_yaw_jitter_deg, cfg.start_yaw_jitter_deg))
            )
            start = Pose(float(start_xyz[0]), float(start_xyz[1]), float(start_xyz[2]), yaw)
            return Route(start, legs, float(flight_z), takeoff_landing=takeoff_landing, with_turn=with_turn)
        raise RouteSamplingFailed(f"no start / goal found around {cfg.max_landmark_tries} landmarks")

    def _first_leg(self, landmark: Landmark, z: float, with_turn: bool, rng: np.random.Generator):
        cfg, centre = self.cfg, landmark_xy(landmark)
        angles = rng.uniform(0.0, 2.0 * math.pi, cfg.max_start_tries)
        radii = rng.uniform(cfg.min_dist_m, cfg.max_dist_m, cfg.max_start_tries)
        starts_xy = centre + radii[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (S, 2)
        starts = np.concatenate([starts_xy, np.full((len(starts_xy), 1), z)], axis=1)
        ok = ~self.pmap.bev_blocked(starts_xy) & self.pmap.is_free(starts)
        for start in starts[ok]:
            goal = _walk_out_of_footprint(self.pmap, centre, start[:2], z)
            if goal is None or np.linalg.norm(goal - start) < cfg.min_goal_dist_m:
                continue
            if with_turn and _straight_line_free(self.pmap, start, goal):
                continue
            return start, RouteLeg(landmark, goal)
        return None

    def _chain(
        self, start_xyz: np.ndarray, first: RouteLeg, landmarks: int, z: float, rng: np.random.Generator
    ) -> list[RouteLeg] | None:
        """`first` and legs to `landmarks - 1` more landmarks, each from the previous goal; None if one fails."""
        legs, origin = [first], start_xyz
        while len(legs) < landmarks:
            leg = self._next_leg(legs[-1], origin, {lg.landmark.landmark_id for lg in legs}, z, rng)
            if leg is None:
                return None
            origin = legs[-1].goal
            legs.append(leg)
        return legs

    def _next_leg(
        self, leg: RouteLeg, origin_xyz: np.ndarray, visited: set[str], z: float, rng: np.random.Generator
    ) -> RouteLeg | None:
        """A leg from `leg`'s goal to a landmark not in `visited`, turning off the heading origin -> goal."""
        cfg = self.cfg
        heading = math.atan2(leg.goal[1] - origin_xyz[1], leg.goal[0] - origin_xyz[0])
        offsets = self._xy - leg.goal[:2]
        dist = np.linalg.norm(offsets, axis=1)
        bearing = np.arctan2(offsets[:, 1], offsets[:, 0])
        change = np.degrees(np.abs((bearing - heading + np.pi) % (2 * np.pi) - np.pi))
        lo, hi = cfg.chain_bearing_deg
        ok = (
            (dist >= cfg.min_dist_m)
            & (dist <= cfg.max_dist_m)
            & (change >= lo)
            & (change <= hi)
            & (self._tops > z - cfg.landmark_top_slack_m)
        )
        for index in rng.permutation(np.flatnonzero(ok))[: cfg.max_start_tries]:
            landmark = self.landmarks[index]
            if landmark.landmark_id in visited:
                continue
            goal = _walk_out_of_footprint(self.pmap, landmark_xy(landmark), leg.goal[:2], z)
            if goal is not None:
                return RouteLeg(landmark, goal)
        return None
